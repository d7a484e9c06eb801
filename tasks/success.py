"""Task success, judged on ground-truth cloth vertices after release and
settling. Plain numpy functions."""

import dataclasses as dc

import numpy as np
from fabric_imitation.learning.state import world_to_object
from fabric_imitation.scenarios.poses import ObjectPlanarPose
from fabric_imitation.scenarios.schema import Scenario
from fabric_imitation.systems.cloth_mesh import TopTriangles


@dc.dataclass
class SuccessReport:
    success: bool
    details: dict


def _covered(points_xy: np.ndarray, tri_xy: np.ndarray) -> np.ndarray:
    """(P,) whether each point lies in any of the (T, 3, 2) triangles."""
    p = points_xy[:, None, :]
    a, b, c = tri_xy[None, :, 0], tri_xy[None, :, 1], tri_xy[None, :, 2]

    def cross(u, v, w):
        return (v[..., 0] - u[..., 0]) * (w[..., 1] - u[..., 1]) - (
            v[..., 1] - u[..., 1]
        ) * (w[..., 0] - u[..., 0])

    d1, d2, d3 = cross(a, b, p), cross(b, c, p), cross(c, a, p)
    neg = (d1 < 0) | (d2 < 0) | (d3 < 0)
    pos = (d1 > 0) | (d2 > 0) | (d3 > 0)
    return np.any(~(neg & pos), axis=1)


def BoxCoverSuccess(
    scenario: Scenario, positions_W: np.ndarray, top_grid: np.ndarray
) -> SuccessReport:
    """The cloth covers at least `success.box_cover_fraction` of the object's
    top face (a box's rectangle, a cylinder's disc) and rests on it: a
    top-face sample point counts as covered when a cloth surface triangle
    lying on the top face (within the rest tolerance) is over it."""
    size = np.array(scenario.object.size)
    tol = scenario.success.rest_tolerance
    p_O = world_to_object(positions_W, ObjectPlanarPose(scenario))
    tris = TopTriangles(top_grid)
    z = p_O[tris, 2].mean(axis=1)
    resting = (z > size[2] - 0.5 * tol) & (z < size[2] + tol)
    n = 21
    gx = np.linspace(-size[0] / 2, size[0] / 2, n)
    gy = np.linspace(-size[1] / 2, size[1] / 2, n)
    samples = np.stack(np.meshgrid(gx, gy, indexing="ij"), -1).reshape(-1, 2)
    if scenario.object.kind == "cylinder":
        samples = samples[np.hypot(*samples.T) <= size[0] / 2 + 1e-9]
    covered = (
        _covered(samples, p_O[tris[resting]][:, :, :2])
        if resting.any()
        else np.zeros(len(samples), bool)
    )
    fraction = float(covered.mean())
    return SuccessReport(
        success=fraction >= scenario.success.box_cover_fraction,
        details={"top_face_covered": round(fraction, 3)},
    )


def HangSuccess(scenario: Scenario, positions_W: np.ndarray) -> SuccessReport:
    """The cloth rests on the top edge of the plate (or the rail's bar), with
    parts hanging on both sides, and does not reach the table."""
    size = np.array(scenario.object.size)
    tol = scenario.success.rest_tolerance
    thickness = scenario.cloth.thickness
    p_O = world_to_object(positions_W, ObjectPlanarPose(scenario))
    x, y, z = p_O[:, 0], p_O[:, 1], p_O[:, 2]
    on_edge = (
        (np.abs(x) <= size[0] / 2)
        & (np.abs(y) <= size[1] / 2 + tol + thickness)
        & (z >= size[2] - tol)
        & (z <= size[2] + tol + 2 * thickness)
    )
    low = z < size[2] - 0.03
    near_side = low & (y < -size[1] / 2)
    far_side = low & (y > size[1] / 2)
    clearance = float(z.min())
    ok = (
        bool(on_edge.any())
        and bool(near_side.any())
        and bool(far_side.any())
        and clearance > scenario.success.hang_table_clearance
    )
    return SuccessReport(
        success=ok,
        details={
            "vertices_on_edge": int(on_edge.sum()),
            "vertices_near_side": int(near_side.sum()),
            "vertices_far_side": int(far_side.sum()),
            "lowest_point": round(clearance, 4),
        },
    )


def TaskSuccess(
    scenario: Scenario, positions_W: np.ndarray, top_grid: np.ndarray
) -> SuccessReport:
    """Success of the scenario's task; the prior scene has no task (False)."""
    positions_W = np.asarray(positions_W).reshape(-1, 3)
    if scenario.task == "box":
        return BoxCoverSuccess(scenario, positions_W, top_grid)
    if scenario.task == "hang":
        return HangSuccess(scenario, positions_W)
    return SuccessReport(success=False, details={"note": "prior scene has no task"})


def InObjectFrame(scenario: Scenario, positions_W: np.ndarray) -> np.ndarray:
    """(N, 3) points in the task object's frame."""
    return world_to_object(positions_W, ObjectPlanarPose(scenario))


def ReachDistances(scenario: Scenario, p_O: np.ndarray) -> np.ndarray:
    """Per vertex (box frame): its horizontal distance [m] beyond the box's
    footprint if it is more than 3 cm above the table, else 0."""
    out = np.maximum(np.abs(p_O[:, :2]) - np.array(scenario.object.size[:2]) / 2, 0)
    return np.where(p_O[:, 2] > 0.03, np.linalg.norm(out, axis=1), 0.0)


def DrapeReach(scenario: Scenario, positions_W: np.ndarray) -> float:
    """Cloth-likeness of a cover: the furthest horizontal distance [m] beyond
    the box's footprint reached by cloth points more than 3 cm above the
    table (a cloth hangs down the sides; a card-like one stands out)."""
    p_O = InObjectFrame(scenario, positions_W)
    return float(ReachDistances(scenario, p_O).max(initial=0.0))


def SideFlapReach(
    scenario: Scenario, positions_W: np.ndarray, corner: float = 0.02
) -> tuple[float, float]:
    """The reach figure of DrapeReach measured only off the middle of the
    box's sides (cloth more than 3 cm up, within `corner` of a side's ends
    left out): (beyond the left / right sides, beyond the front / back)
    [m]. At the back corners a cloth pulled from behind rises from the
    table as a sloping wing, which DrapeReach's maximum picks up."""
    p_O = InObjectFrame(scenario, positions_W)
    half = np.array(scenario.object.size[:2]) / 2
    high = p_O[:, 2] > 0.03
    out = np.maximum(np.abs(p_O[:, :2]) - half, 0)
    along_x = high & (np.abs(p_O[:, 1]) <= half[1] - corner)
    along_y = high & (np.abs(p_O[:, 0]) <= half[0] - corner)
    return (
        float(out[along_x, 0].max(initial=0.0)),
        float(out[along_y, 1].max(initial=0.0)),
    )
