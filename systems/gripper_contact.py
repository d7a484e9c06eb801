"""Gripper shapes and the gripper-object contact monitor.

A gripper is the Franka hand of `example-robot-data`'s
`panda_collision.urdf`: its collision model is capsules (a cylinder with
spheres of the same radius on its ends), one for the hand and one per
finger. `PandaHandCapsules` gives them in a grasp frame G at the grasped
point, fingers closed on the cloth and pointing down, so that the anchor
grippers can carry the same shape as collision geometry.

`GripperObjectContact` checks every plant step whether any gripper capsule
penetrates the task object (its shape: learning/object_shape.py), and
latches the first time it does: the benchmark's collision event. It computes
the distance itself rather than asking SceneGraph, so it judges the Panda
arms too, whose collisions the station filters out.
"""

import dataclasses as dc

import numpy as np
from fabric_imitation.learning.object_shape import ObjectSignedDistance
from fabric_imitation.scenarios.schema import Scenario
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.framework import EventStatus, LeafSystem


@dc.dataclass(frozen=True)
class Capsule:
    """A segment p_a-p_b [m] swept by a sphere of `radius` [m], in a body's
    frame."""

    p_a: tuple[float, float, float]
    p_b: tuple[float, float, float]
    radius: float

    def samples(self, spacing_fraction: float = 0.1) -> np.ndarray:
        """(n, 3) points along the axis, at most `spacing_fraction` x radius
        apart: spheres of the capsule's radius at these points cover it to
        within radius x (1 - sqrt(1 - (spacing_fraction / 2)^2)) (0.13 % at
        0.1: 0.06 mm on the hand's 5 cm, under the 0.15 mm a hand resting on
        the object sinks in)."""
        a, b = np.array(self.p_a), np.array(self.p_b)
        n = int(np.ceil(np.linalg.norm(b - a) / (spacing_fraction * self.radius)))
        return a + np.linspace(0.0, 1.0, max(n, 1) + 1)[:, None] * (b - a)


# The Franka hand of example-robot-data's panda_collision.urdf, fingers
# closed (1 mm apart) on the cloth, in a grasp frame G whose origin is the
# fingertips' lowest point and whose z axis points up, from the fingertips
# to the hand; y is the axis the fingers close along. In the hand's own frame
# the fingers' capsules run from z = 0.0734 to 0.1034 (radius 1.5 cm, their
# tips 1.5 cm below the tool centre point at z = 0.1034) and the hand's from
# y = -0.075 to 0.075 at z = 0.03 (radius 5 cm); G's height above the tips
# is 0.1184 - z.
_TIPS = 0.1184
_FINGER_Y = 0.015 + 0.0005


def PandaHandCapsules() -> tuple[Capsule, ...]:
    """The hand and both fingers of a grasping Franka hand, in the grasp frame
    G (origin at the fingertips' lowest point, z up, fingers closing along
    y)."""
    fingers = tuple(
        Capsule(
            (0.0, s * _FINGER_Y, _TIPS - 0.1034),
            (0.0, s * _FINGER_Y, _TIPS - 0.0734),
            0.015,
        )
        for s in (1.0, -1.0)
    )
    hand = Capsule((0.0, -0.075, _TIPS - 0.03), (0.0, 0.075, _TIPS - 0.03), 0.05)
    return (hand, *fingers)


def PandaLinkCapsules() -> dict[str, tuple[Capsule, ...]]:
    """The same capsules in the frames of the Panda model's own links (as
    `panda_collision.urdf` places them)."""
    return {
        "panda_hand": (Capsule((0.0, -0.075, 0.03), (0.0, 0.075, 0.03), 0.05),),
        "panda_leftfinger": (Capsule((0.0, 0.015, 0.015), (0.0, 0.015, 0.045), 0.015),),
        "panda_rightfinger": (
            Capsule((0.0, -0.015, 0.015), (0.0, -0.015, 0.045), 0.015),
        ),
    }


@dc.dataclass(frozen=True)
class GripperBody:
    """A plant body that belongs to a gripper and its capsules (body frame)."""

    body_index: int
    capsules: tuple[Capsule, ...]
    name: str


def CapsulesPenetration(
    capsules: tuple[Capsule, ...],
    X_OB: RigidTransform,
    object_kind: str,
    object_size: np.ndarray,
) -> float:
    """The deepest penetration [m] of the capsules (body frame B, the body
    at X_OB in the object's frame) into the object (> 0), or the smallest
    clearance as a negative number."""
    pts = np.vstack([c.samples() for c in capsules])
    radii = np.concatenate([np.full(len(c.samples()), c.radius) for c in capsules])
    p_O = X_OB.multiply(pts.T).T
    return float((radii - ObjectSignedDistance(p_O, object_kind, object_size)).max())


class GripperObjectContact(LeafSystem):
    """Whether a gripper touches the task object, checked every plant step.

    Simulation only (it reads the plant's true body poses).

    Input ports: ``body_poses`` (the plant's `get_body_poses_output_port()`:
    a list of RigidTransform X_WB by body index).
    Output ports: ``contact`` (3: plant steps on which any gripper capsule
    penetrated the object so far, the time of the first [s] (-1: none), the
    deepest penetration so far [m], 0 if none); from state.
    """

    def __init__(
        self,
        *,
        grippers: list[GripperBody],
        X_WO: RigidTransform,
        object_kind: str,
        object_size: np.ndarray,
        period: float,
    ):
        super().__init__()
        self._kind = object_kind
        self._size = np.asarray(object_size, float)
        self._X_OW = X_WO.inverse()
        # Per body: its capsules' axis samples (n, 3) and radii (n,).
        self._bodies = []
        for g in grippers:
            pts = [c.samples() for c in g.capsules]
            radii = [
                np.full(len(p), c.radius) for p, c in zip(pts, g.capsules, strict=True)
            ]
            self._bodies.append((g.body_index, np.vstack(pts), np.concatenate(radii)))
        self._poses = self.DeclareAbstractInputPort(
            "body_poses", AbstractValue.Make([RigidTransform()])
        )
        self._state = self.DeclareDiscreteState(np.array([0.0, -1.0, 0.0]))
        self.DeclarePeriodicDiscreteUpdateEvent(period, 0.0, self._update)
        self.DeclareStateOutputPort("contact", self._state)

    def Penetration(self, poses: list[RigidTransform]) -> float:
        """The deepest penetration [m] of any gripper capsule into the
        object (> 0), or the smallest clearance as a negative number."""
        deepest = -np.inf
        for index, pts, radii in self._bodies:
            p_O = (self._X_OW @ poses[index]).multiply(pts.T).T
            depth = radii - ObjectSignedDistance(p_O, self._kind, self._size)
            deepest = max(deepest, float(depth.max()))
        return deepest

    def _update(self, context, discrete_state) -> EventStatus:
        steps, first, deepest = context.get_discrete_state(self._state).value()
        depth = self.Penetration(self._poses.Eval(context))
        if depth > 0.0:
            steps += 1
            first = context.get_time() if first < 0 else first
            deepest = max(deepest, depth)
        discrete_state.get_mutable_vector(self._state).SetFromVector(
            [steps, first, deepest]
        )
        return EventStatus.Succeeded()


# The anchors' hands: the grasp frame of PandaHandCapsules turned so the
# fingers close along the world's diagonal, as the station's Panda hands do
# (panda.HandOrientation at the default base yaw of 90 degrees).
ANCHOR_CAPSULES = PandaHandCapsules()


ANCHOR_HAND_YAW = RotationMatrix.MakeZRotation(np.pi / 4)


# The Panda's tool centre point holds the corner with the fingertips this far
# [m] below it (panda_collision.urdf); the anchors hold it at the tips.
PANDA_TIPS_BELOW_TCP = 0.015


def GraspCapsules(scenario: Scenario) -> tuple[Capsule, ...]:
    """The hand capsules of the scenario's grippers around the grasped point
    (world-aligned; the Panda's turned as the anchors')."""
    if scenario.grippers.kind != "panda":
        return AnchorHandCapsules()
    down = np.array([0.0, 0.0, PANDA_TIPS_BELOW_TCP])
    return tuple(
        Capsule(tuple(np.array(c.p_a) - down), tuple(np.array(c.p_b) - down), c.radius)
        for c in AnchorHandCapsules()
    )


def AnchorHandCapsules() -> tuple[Capsule, ...]:
    """The anchors' hand capsules in the anchor's (world-aligned) frame."""
    return tuple(
        Capsule(
            tuple(ANCHOR_HAND_YAW @ np.array(c.p_a)),
            tuple(ANCHOR_HAND_YAW @ np.array(c.p_b)),
            c.radius,
        )
        for c in ANCHOR_CAPSULES
    )
