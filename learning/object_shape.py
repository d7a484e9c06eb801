"""The task object's solid shape in its own frame O (x, y centred, z up from
the table at z = 0), as boxes and cylinders, and the signed distance to it
(numpy and torch, batched). Every part of the project that asks whether a
point is inside the object (the cloth simulator's held particles, the safety
rules' object rule, the gripper-object contact monitor) reads it from here,
so a new object kind is added in one place.

Kinds and what `size` = [sx, sy, sz] means for each:

- ``box``: a box sx x sy x sz;
- ``plate``: the same, thin in y (a plate standing on its edge);
- ``cylinder``: a standing can of diameter sx (= sy) and height sz;
- ``rail``: a towel rail sx wide overall and sz high: a round bar of
  diameter sy along x, its top at sz, on two square posts sy x sy at its
  ends, from the table to the bar's axis.

`size` is always the shape's bounding box.
"""

import dataclasses as dc

import numpy as np
import torch

SHAPED_KINDS = ("box", "plate", "cylinder", "rail")


@dc.dataclass(frozen=True)
class ShapePart:
    """A box (``size``: full extents x, y, z) or a cylinder (``size``:
    diameter, diameter, length; its axis along ``axis``, "x" or "z") centred
    at ``centre`` in O."""

    kind: str
    centre: tuple[float, float, float]
    size: tuple[float, float, float]
    axis: str = "z"


def ObjectParts(kind: str, size) -> tuple[ShapePart, ...]:
    """The parts of an object of `kind` and bounding box `size` (module
    docstring), in O."""
    sx, sy, sz = (float(v) for v in size)
    if kind in ("box", "plate"):
        return (ShapePart("box", (0.0, 0.0, sz / 2), (sx, sy, sz)),)
    if kind == "cylinder":
        return (ShapePart("cylinder", (0.0, 0.0, sz / 2), (sx, sx, sz)),)
    if kind == "rail":
        axis_z = sz - sy / 2
        post_x = sx / 2 - sy / 2
        posts = tuple(
            ShapePart("box", (s * post_x, 0.0, axis_z / 2), (sy, sy, axis_z))
            for s in (-1.0, 1.0)
        )
        bar = ShapePart("cylinder", (0.0, 0.0, axis_z), (sy, sy, sx), axis="x")
        return (*posts, bar)
    raise ValueError(f"unknown object kind {kind!r} (one of {', '.join(SHAPED_KINDS)})")


def _part_distance(p: torch.Tensor, part: ShapePart) -> torch.Tensor:
    """Signed distance of points p (..., 3) in O to one part."""
    c = p - torch.as_tensor(part.centre, dtype=p.dtype)
    if part.kind == "box":
        q = c.abs() - torch.as_tensor(part.size, dtype=p.dtype) / 2
    else:
        # A cylinder: its radial and axial distances, combined as for a
        # 2-D box.
        along = 0 if part.axis == "x" else 2
        across = [k for k in range(3) if k != along]
        radial = torch.linalg.norm(c[..., across], dim=-1) - part.size[0] / 2
        q = torch.stack([radial, c[..., along].abs() - part.size[2] / 2], -1)
    outside = torch.linalg.norm(q.clamp(min=0.0), dim=-1)
    return outside + q.max(dim=-1).values.clamp(max=0.0)


def object_signed_distance(p: torch.Tensor, kind: str, size) -> torch.Tensor:
    """Signed distance [m] of points p (..., 3) in O to the object, negative
    inside, in p's dtype."""
    parts = ObjectParts(kind, size)
    d = _part_distance(p, parts[0])
    for part in parts[1:]:
        d = torch.minimum(d, _part_distance(p, part))
    return d


def ObjectSignedDistance(p_O, kind: str, size) -> np.ndarray:
    """object_signed_distance for numpy points (float64)."""
    p = torch.as_tensor(np.asarray(p_O, float), dtype=torch.float64)
    return object_signed_distance(p, kind, size).numpy()
