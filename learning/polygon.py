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

    Along an edge of A the inside/outside status flips at each crossing with
    B's boundary, so only each edge's start needs a point-in-polygon test.
    That test is made a hair along the edge and to its left (side = +1) or
    right (-1), so that an edge shared by A and B counts once.
    """
    r = A[..., :, None, :]  # (..., K, 1, 2) edge starts
    s = (A.roll(-1, -2) - A)[..., :, None, :]  # edge vectors
    q0 = B[..., None, :, :]  # (..., 1, L, 2)
    e = (B.roll(-1, -2) - B)[..., None, :, :]
    denom = s[..., 0] * e[..., 1] - s[..., 1] * e[..., 0]  # (..., K, L)
    dx, dy = q0[..., 0] - r[..., 0], q0[..., 1] - r[..., 1]
    safe = torch.where(denom.abs() < 1e-12, torch.ones_like(denom), denom)
    t = (dx * e[..., 1] - dy * e[..., 0]) / safe  # along A's edge
    u = (dx * s[..., 1] - dy * s[..., 0]) / safe  # along B's edge
    valid = (denom.abs() >= 1e-12) & (t > 0) & (t < 1) & (u >= 0) & (u <= 1)
    t = torch.where(valid, t, torch.ones_like(t))  # non-crossings go to the end
    t, _ = torch.sort(t, -1)
    zero = torch.zeros_like(t[..., :1])
    cuts = torch.cat([zero, t], -1)  # (..., K, L + 1): piece i is [cuts_i, cuts_i+1]
    t0, t1 = cuts, torch.cat([t, torch.ones_like(zero)], -1)
    # Inside status of each edge's start, tested a hair along and beside it.
    length = s[..., 0, :].norm(dim=-1, keepdim=True).clamp_min(1e-12)
    along = s[..., 0, :] / length
    normal = torch.stack([-along[..., 1], along[..., 0]], -1)
    probe = A + NUDGE * (along + side * normal)  # (..., K, 2)
    start_in = _inside(probe, B)  # (..., K)
    parity = torch.arange(cuts.shape[-1]) % 2 == 1
    inside = start_in[..., None] ^ parity  # (..., K, L + 1)
    x0 = r[..., 0] + t0 * s[..., 0]
    x1 = r[..., 0] + t1 * s[..., 0]
    piece = 0.5 * (x0 + x1) * (t1 - t0) * s[..., 1]
    return (piece * inside).sum((-1, -2))


def intersection_area(A: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    lead = torch.broadcast_shapes(A.shape[:-2], B.shape[:-2])
    A = ccw(A).expand(*lead, *A.shape[-2:])
    B = ccw(B).expand(*lead, *B.shape[-2:])
    return (_boundary_inside(A, B, 1.0) + _boundary_inside(B, A, -1.0)).clamp_min(0.0)


def iou(A: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """Intersection over union (...) of polygons A, B (..., K, 2)."""
    inter = intersection_area(A, B)
    union = signed_area(A).abs() + signed_area(B).abs() - inter
    return inter / union.clamp_min(1e-12)
