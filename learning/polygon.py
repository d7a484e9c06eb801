"""Exact, batched area and intersection-over-union of planar polygons (torch).

The intersection area comes from Green's theorem: the boundary of A n B is
the part of A's boundary inside B plus the part of B's boundary inside A, and
area = integral of x dy along it. Each edge is cut at its crossings with the
other polygon's edges, and the pieces inside the other polygon are integrated
in closed form. This is exact for simple polygons of any shape (convex or
not); polygons are first made counter-clockwise.

Shapes: polygons (..., K, 2); everything broadcasts over the leading dims.
"""

import torch
from fabric_imitation.learning import polygon_kernel

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


def intersection_area(A: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """Area (...) of A n B by Green's theorem along both boundaries at once.

    Along A's edge k, p(t) = a_k + t s_k, the integral of x dy from 0 to t is
    F(t) = s_y (a_x t + s_x t^2 / 2) (likewise G(u) along B's edge l). The
    part of an edge inside the other polygon is a union of intervals between
    crossings, so its integral is sum_c sign_c F(t_c) + [edge end inside]
    F(1), with sign +1 where the edge leaves the other polygon and -1 where it
    enters. Each crossing of A's edge k with B's edge l is computed once and
    serves both boundaries: where A leaves B, B enters A. Whether a vertex is
    inside the other polygon follows from one point-in-polygon test for
    vertex 0 and the parity of the crossings along the boundary after it.
    """
    lead = torch.broadcast_shapes(A.shape[:-2], B.shape[:-2])
    A = ccw(A).expand(*lead, *A.shape[-2:])
    # A tiny, generic shift of B removes the degenerate cases (collinear
    # overlapping edges, a vertex exactly on the other's edge) that hand-made
    # and axis-aligned polygons have; it changes areas by ~1e-6 * perimeter.
    B = ccw(B).expand(*lead, *B.shape[-2:]) + B.new_tensor(SHIFT)
    s = A.roll(-1, -2) - A  # (..., K, 2) edge vectors of A
    e = B.roll(-1, -2) - B  # (..., L, 2) edge vectors of B
    sx, sy = s[..., :, None, 0], s[..., :, None, 1]  # (..., K, 1)
    ex, ey = e[..., None, :, 0], e[..., None, :, 1]  # (..., 1, L)
    ax, bx = A[..., :, None, 0], B[..., None, :, 0]
    dx, dy = bx - ax, B[..., None, :, 1] - A[..., :, None, 1]
    denom = sx * ey - sy * ex  # (..., K, L)
    ok = denom.abs() >= 1e-12
    inv = 1.0 / torch.where(ok, denom, torch.ones_like(denom))
    t = (dx * ey - dy * ex) * inv  # along A's edge
    u = (dx * sy - dy * sx) * inv  # along B's edge
    valid = ok & (t > 0) & (t < 1) & (u > 0) & (u < 1)
    # denom = cross(s, e) > 0: A's edge goes to the right of B's, i.e. leaves
    # B, and B's edge enters A.
    sign = torch.where(denom > 0, 1.0, -1.0)
    F = sy * (ax * t + 0.5 * sx * t * t)
    G = ey * (bx * u + 0.5 * ex * u * u)
    crossings = torch.where(valid, sign * (F - G), torch.zeros_like(F)).sum((-1, -2))
    # End of edge k inside the other polygon: vertex 0's test flipped by
    # every crossing on edges 0..k.
    end_a = _inside(A[..., :1, :], B) ^ (valid.sum(-1).cumsum(-1) % 2 == 1)
    end_b = _inside(B[..., :1, :], A) ^ (valid.sum(-2).cumsum(-1) % 2 == 1)
    F1 = s[..., 1] * (A[..., 0] + 0.5 * s[..., 0])
    G1 = e[..., 1] * (B[..., 0] + 0.5 * e[..., 0])
    inside = (end_a * F1).sum(-1) + (end_b * G1).sum(-1)
    return (crossings + inside).clamp_min(0.0)


def iou(A: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """Intersection over union (...) of polygons A, B (..., K, 2)."""
    inter = intersection_area(A, B)
    union = signed_area(A).abs() + signed_area(B).abs() - inter
    return inter / union.clamp_min(1e-12)


def iou_pairs(A: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """IoU (P, W) float32 of every polygon of A (P, K, 2) with every polygon
    of B (W, L, 2): `iou`'s algorithm, in double precision, by the compiled
    kernel of `polygon_kernel.c` (about 20x faster than `iou` in torch for
    the MPC's thousands of pairs), or by `iou` in float64 where no C compiler
    is found (or for polygons of more than polygon_kernel.MAX_VERTICES
    vertices). Both agree with `iou` in float64 to 1e-6."""
    if A.dim() != 3 or B.dim() != 3 or A.shape[-1] != 2 or B.shape[-1] != 2:
        raise ValueError(
            f"iou_pairs needs (P, K, 2) and (W, L, 2), got {tuple(A.shape)} "
            f"and {tuple(B.shape)}"
        )
    kernel = polygon_kernel.load()
    sizes_ok = all(
        3 <= n <= polygon_kernel.MAX_VERTICES for n in (A.shape[1], B.shape[1])
    )
    if kernel is None or not sizes_ok or A.is_cuda or B.is_cuda:
        out = iou(A.double()[:, None], B.double()[None])
        return out.float()
    a = A.detach().to(torch.float32).contiguous()
    b = B.detach().to(torch.float32).contiguous()
    out = torch.empty(len(a), len(b), dtype=torch.float32)
    if len(a) and len(b):
        kernel(a, b, SHIFT, out)
    return out
