"""Exact, batched area and intersection-over-union of planar polygons (torch).

The intersection area comes from Green's theorem: the boundary of A n B is
the part of A's boundary inside B plus the part of B's boundary inside A, and
area = integral of x dy along it. Each edge of A is cut at its crossings with
B's edges; each piece whose midpoint lies inside B contributes
(x0 + x1) / 2 * (y1 - y0). This is exact for simple polygons of any shape
(convex or not); polygons are first made counter-clockwise.

Shapes: polygons (..., K, 2); everything broadcasts over the leading dims.
"""

import torch

NUDGE = 1e-6  # [m] sideways offset of the inside test, above float32 resolution
SHIFT = (3.1e-6, 1.7e-6)  # [m] generic offset of the second polygon


def signed_area(P: torch.Tensor) -> torch.Tensor:
    x, y = P[..., 0], P[..., 1]
    return 0.5 * (x * y.roll(-1, -1) - x.roll(-1, -1) * y).sum(-1)


def ccw(P: torch.Tensor) -> torch.Tensor:
    """P with its vertex order reversed where it is clockwise."""
    flip = signed_area(P) < 0
    return torch.where(flip[..., None, None], P.flip(-2), P)


def _inside(points: torch.Tensor, poly: torch.Tensor) -> torch.Tensor:
    """Even-odd test of points (..., Q, 2) against polygons (..., K, 2)."""
    px, py = points[..., :, None, 0], points[..., :, None, 1]
    a = poly[..., None, :, :]
    b = poly.roll(-1, -2)[..., None, :, :]
    ay, by, ax, bx = a[..., 1], b[..., 1], a[..., 0], b[..., 0]
    crosses = (ay > py) != (by > py)
    t = (py - ay) / torch.where(by == ay, torch.ones_like(by), by - ay)
    x_at = ax + t * (bx - ax)
    hits = crosses & (px < x_at)
    return (hits.sum(-1) % 2) == 1


def _boundary_inside(A: torch.Tensor, B: torch.Tensor, side: float) -> torch.Tensor:
    """Integral of x dy along the part of A's boundary inside B, (...).

    Along A's edge k, p(t) = a_k + t s_k, the integral from 0 to t is
    F(t) = s_y (a_x t + s_x t^2 / 2). The inside part of the edge is a union
    of intervals between crossings with B's boundary, so its integral is
    sum_c sign_c F(t_c) + [edge end inside] F(1), with sign +1 where A leaves
    B and -1 where it enters (read off the crossing's geometry, so no sorting).
    Only each edge's start needs a point-in-polygon test; it is made a hair
    along the edge and to its left (side = +1) or right (-1), so that an edge
    shared by A and B counts once.
    """
    a = A[..., :, None, :]  # (..., K, 1, 2) edge starts
    s = (A.roll(-1, -2) - A)[..., :, None, :]  # edge vectors
    e = (B.roll(-1, -2) - B)[..., None, :, :]  # (..., 1, L, 2)
    dx = B[..., None, :, 0] - a[..., 0]
    dy = B[..., None, :, 1] - a[..., 1]
    denom = s[..., 0] * e[..., 1] - s[..., 1] * e[..., 0]  # (..., K, L)
    ok = denom.abs() >= 1e-12
    safe = torch.where(ok, denom, torch.ones_like(denom))
    t = (dx * e[..., 1] - dy * e[..., 0]) / safe  # along A's edge
    u = (dx * s[..., 1] - dy * s[..., 0]) / safe  # along B's edge
    valid = ok & (t > 0) & (t < 1) & (u >= 0) & (u <= 1)
    sx, sy, ax = s[..., 0], s[..., 1], a[..., 0]
    F = sy * (ax * t + 0.5 * sx * t * t)
    # denom = cross(s, e) > 0: A's edge goes to the right of B's, i.e. leaves.
    sign = torch.where(denom > 0, 1.0, -1.0)
    crossings = (torch.where(valid, sign * F, torch.zeros_like(F))).sum(-1)
    length = s[..., 0, :].norm(dim=-1, keepdim=True).clamp_min(1e-12)
    along = s[..., 0, :] / length
    normal = torch.stack([-along[..., 1], along[..., 0]], -1)
    probe = A + NUDGE * (along + side * normal)  # (..., K, 2)
    start_in = _inside(probe, B)  # (..., K)
    end_in = start_in ^ (valid.sum(-1) % 2 == 1)
    F1 = sy[..., 0] * (ax[..., 0] + 0.5 * sx[..., 0])
    return (crossings + end_in * F1).sum(-1)


def intersection_area(A: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    lead = torch.broadcast_shapes(A.shape[:-2], B.shape[:-2])
    A = ccw(A).expand(*lead, *A.shape[-2:])
    # A tiny, generic shift of B removes the degenerate cases (collinear
    # overlapping edges, a vertex exactly on the other's edge) that hand-made
    # and axis-aligned polygons have; it changes areas by ~1e-6 * perimeter.
    B = ccw(B).expand(*lead, *B.shape[-2:]) + B.new_tensor(SHIFT)
    return (_boundary_inside(A, B, 1.0) + _boundary_inside(B, A, -1.0)).clamp_min(0.0)


def iou(A: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """Intersection over union (...) of polygons A, B (..., K, 2)."""
    inter = intersection_area(A, B)
    union = signed_area(A).abs() + signed_area(B).abs() - inter
    return inter / union.clamp_min(1e-12)


_COMPILED = {}


def iou_batched(A: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """`iou` through torch.compile (fused C++ kernels, about 5x faster on CPU
    for the MPC's thousands of pairs); compiled once per input shape, at a
    cost of about half a minute; falls back to `iou` if compiling fails."""
    key = (tuple(A.shape), tuple(B.shape), A.dtype)
    fn = _COMPILED.get(key)
    if fn is None:
        try:
            fn = torch.compile(iou, dynamic=False)
            fn(A, B)
        except Exception:  # noqa: BLE001 (no compiler here: stay eager)
            fn = iou
        _COMPILED[key] = fn
    return fn(A, B)
