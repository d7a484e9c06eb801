"""Where a scenario puts things on the table: planar poses as transforms, the
cloth's frame at rest and its grasped corners."""

import numpy as np
from fabric_imitation.scenarios.schema import Scenario, yaw_rad
from pydrake.math import RigidTransform, RotationMatrix


def PoseOnTable(pose: list[float], z: float = 0.0) -> RigidTransform:
    """X_W* of an [x, y, yaw_deg] pose on the table top, lifted by z."""
    return RigidTransform(
        RotationMatrix.MakeZRotation(yaw_rad(pose)), [pose[0], pose[1], z]
    )


def GraspCorners(scenario: Scenario) -> dict[str, np.ndarray]:
    """World positions of the grasped corners (top face) at the start."""
    cloth = scenario.cloth
    X_WC = ClothPose(scenario)
    hx, hy, hz = cloth.size[0] / 2, cloth.size[1] / 2, cloth.thickness / 2
    return {
        "left": X_WC @ np.array([-hx, -hy, hz]),
        "right": X_WC @ np.array([hx, -hy, hz]),
    }


def ClothPose(scenario: Scenario) -> RigidTransform:
    """X_WC of the cloth frame C (the slab's centre) at rest on the table."""
    return PoseOnTable(scenario.cloth.pose, scenario.cloth.thickness / 2)


def ObjectPlanarPose(scenario: Scenario) -> np.ndarray:
    """[x, y, yaw (rad)] of the task object on the table."""
    pose = scenario.object.pose
    return np.array([pose[0], pose[1], yaw_rad(pose)])
