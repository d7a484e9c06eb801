"""What the robot's driver enforces on every method's moves, whatever chose
them: a per-axis bound on each step and a reach box for the gripper targets
(the scenario's workspace, in world) above the table top.

This is not the paper's safe action set (learning/safety.py): no rule on the
cloth, its corners or the object. The baselines (learning/baselines.py) use
only this; the method's MPC bounds its samples the same way and adds the
rules on top.

Shapes: gripper positions (..., 2, 3) [s1, s2] and actions (..., 6) =
[a_L, a_R], in the frame of the states (an object frame at planar pose
[x, y, yaw_rad] in world, or world itself); torch, batched.
"""

import dataclasses as dc
import math

import numpy as np
import torch
from fabric_imitation.learning.state import corner_indices


@dc.dataclass
class DriverLimits:
    # [m] largest move of a gripper per axis per control step.
    max_step: float
    # (3,) [m] the grippers' reach box in world (the scenario's workspace).
    workspace_lower: np.ndarray
    workspace_upper: np.ndarray
    # [m] lowest gripper target height in world (the table top is z = 0).
    floor: float = 0.0

    def __post_init__(self):
        self.workspace_lower = np.asarray(self.workspace_lower, float).reshape(3)
        self.workspace_upper = np.asarray(self.workspace_upper, float).reshape(3)
        if not self.max_step > 0:
            raise ValueError(f"max_step must be positive, got {self.max_step}")
        lower = self.workspace_lower.copy()
        lower[2] = max(lower[2], self.floor)
        if not (lower < self.workspace_upper).all():
            raise ValueError(
                "workspace_lower (raised to the floor) must lie below "
                f"workspace_upper, got {lower} and {self.workspace_upper}"
            )

    @classmethod
    def FromSafety(cls, safety, ctx) -> "DriverLimits":
        """The driver's part of a SafetyConfig and SafetyContext: max_step and
        the workspace box, nothing else (no rule on the cloth)."""
        return cls(
            max_step=float(safety.max_step),
            workspace_lower=ctx.workspace_lower,
            workspace_upper=ctx.workspace_upper,
        )


def gripper_positions(S: torch.Tensor) -> torch.Tensor:
    """The grasped corners s1, s2 (..., 2, 3) of states S (..., M, 3): where
    the grippers are (the estimator puts the measured grippers there)."""
    idx = corner_indices(S.shape[-2])
    return S[..., [idx["s1"], idx["s2"]], :]


def limit_actions(
    grippers: torch.Tensor, A: torch.Tensor, limits: DriverLimits, frame_pose=None
) -> torch.Tensor:
    """Actions A (..., 6) as the driver executes them from gripper positions
    (..., 2, 3): each gripper's target moved into the reach box (world, above
    `floor`), then each axis of the move clamped to +-max_step (the bound
    wins where a gripper starts outside the box). `frame_pose`: [x, y,
    yaw_rad] of the states' frame in world (None: world)."""
    A = torch.as_tensor(A, dtype=torch.float32)
    g = torch.as_tensor(grippers, dtype=A.dtype)
    b = limits.max_step
    A = A.clamp(-b, b)
    x, y, yaw = (0.0, 0.0, 0.0) if frame_pose is None else map(float, frame_pose)
    c, s = math.cos(yaw), math.sin(yaw)
    R = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=A.dtype)
    t = torch.tensor([x, y, 0.0], dtype=A.dtype)
    lower = torch.as_tensor(limits.workspace_lower, dtype=A.dtype).clone()
    lower[2] = max(float(lower[2]), limits.floor)
    upper = torch.as_tensor(limits.workspace_upper, dtype=A.dtype)
    target_W = (g + A.unflatten(-1, (2, 3))) @ R.T + t
    target_W = torch.maximum(torch.minimum(target_W, upper), lower)
    moved = ((target_W - t) @ R - g).flatten(-2)
    return moved.clamp(-b, b)
