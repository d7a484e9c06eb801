"""The cloth state S: M ordered boundary keypoints in 3-D (paper Sec. IV-B).

Order: counter-clockwise seen from above, starting at the left grasped corner
s1. With the cloth's grasped edge at its local -y side and "left" at local -x
(the robot looks along +y), M = 4k keypoints are the four corners and k - 1
evenly spaced points on each edge:

    index 0      s1, left grasped corner
    index k      s2, right grasped corner
    index 2k     s4, right far corner
    index 3k     s3, left far corner

so the grasped edge is indices 0..k, and the polygon closes back to index 0.
"""

from typing import NamedTuple

import numpy as np

# The two grippers, left first (the robot looks along +y).
SIDES = ("left", "right")
# M, the keypoints of the cloth state every model and scene uses.
NUM_KEYPOINTS = 8


def corner_indices(m: int) -> dict[str, int]:
    """Positions of s1 (left grasp), s2 (right grasp), s3 (left far), s4 (right
    far) in a state with m keypoints."""
    check_num_keypoints(m)
    k = m // 4
    return {"s1": 0, "s2": k, "s4": 2 * k, "s3": 3 * k}


def check_num_keypoints(m: int) -> None:
    if m < 4 or m % 4:
        raise ValueError(f"number of keypoints must be a multiple of 4, got {m}")


def boundary_grid_indices(m: int, nx: int, ny: int) -> list[tuple[int, int]]:
    """(i, j) grid positions of the m keypoints on an nx-by-ny vertex grid
    (i along local x, j along local y), in keypoint order."""
    check_num_keypoints(m)
    k = m // 4

    def along(n: int, s: int) -> int:
        return int(round(s * (n - 1) / k))

    out = []
    for s in range(k):  # grasped edge, left -> right (j = 0)
        out.append((along(nx, s), 0))
    for s in range(k):  # right edge, near -> far (i = nx - 1)
        out.append((nx - 1, along(ny, s)))
    for s in range(k):  # far edge, right -> left (j = ny - 1)
        out.append((nx - 1 - along(nx, s), ny - 1))
    for s in range(k):  # left edge, far -> near (i = 0)
        out.append((0, ny - 1 - along(ny, s)))
    return out


def yaw_matrix(yaw: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) about z for yaw angles (...) in radians."""
    c, s = np.cos(yaw), np.sin(yaw)
    z, o = np.zeros_like(c), np.ones_like(c)
    return np.stack(
        [np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)],
        -2,
    )


class PlanarPose(NamedTuple):
    """A pose on the table: position [m] and yaw about z [rad] (the object
    frame O; z up, on the table top). The one type for `[x, y, yaw]`."""

    x: float
    y: float
    yaw: float

    @classmethod
    def FromDegrees(cls, pose) -> "PlanarPose":
        """From a scenario's `[x, y, yaw_deg]`."""
        return cls(float(pose[0]), float(pose[1]), float(np.radians(pose[2])))

    @classmethod
    def FromRigidTransform(cls, X) -> "PlanarPose":
        """From a pydrake RigidTransform (its yaw; roll and pitch ignored)."""
        R = X.rotation().matrix()
        p = X.translation()
        return cls(float(p[0]), float(p[1]), float(np.arctan2(R[1, 0], R[0, 0])))

    def rotation(self) -> np.ndarray:
        """R_WO (3, 3)."""
        return yaw_matrix(np.asarray(self.yaw))

    def vector_to_world(self, v_O: np.ndarray) -> np.ndarray:
        """Vectors (..., 3) from O to world (rotation only, e.g. moves)."""
        return np.asarray(v_O) @ self.rotation().T

    def vector_to_object(self, v_W: np.ndarray) -> np.ndarray:
        """Vectors (..., 3) from world to O (rotation only)."""
        return np.asarray(v_W) @ self.rotation()


def world_to_object(p_W: np.ndarray, pose_O: np.ndarray) -> np.ndarray:
    """Points (..., 3) from world to the object frame O given by [x, y, yaw_rad]
    (O on the table top, z up)."""
    pose_O = np.asarray(pose_O, dtype=float)
    R = yaw_matrix(np.asarray(pose_O[2]))
    t = np.array([pose_O[0], pose_O[1], 0.0])
    return (np.asarray(p_W) - t) @ R


def object_to_world(p_O: np.ndarray, pose_O: np.ndarray) -> np.ndarray:
    """Inverse of world_to_object."""
    pose_O = np.asarray(pose_O, dtype=float)
    R = yaw_matrix(np.asarray(pose_O[2]))
    t = np.array([pose_O[0], pose_O[1], 0.0])
    return np.asarray(p_O) @ R.T + t
