"""The benchmark's referee: the paper's four rules of the safe action set,
judged on the simulator's true keypoints, with thresholds that belong to the
task, not to the method.

The controller has its own copy of the rules (`scenario.safety`, which the
method may tune and extend with hypotheses about hidden corners); the
referee's thresholds are fixed here, per task, and every trial line carries
their fingerprint. They are the loosest that still mean something and the
strictest that the task's scripted demo keeps (0 breaks at the nominal pose
and at moved poses: `fabric-imitate evaluate --methods scripted` reports the
referee's breaks and the gripper-object collisions of each trial).

An episode in simulation ends as a failure at the first executed action
that breaks a rule on the true cloth, or at the first gripper-object
contact (`--on-violation stop`, the default), as the paper's evaluation
stops "an imitation episode in advance" when the optimiser's solution
violates the constraints (Sec. V-C); `--on-violation count` only counts.
"""

import dataclasses as dc
import hashlib
import json

import numpy as np
import torch
from fabric_imitation.learning.errors import InputError
from fabric_imitation.learning.safety import (
    RULES,
    SafetyConfig,
    SafetyContext,
    rule_violations,
)
from fabric_imitation.learning.state import PlanarPose
from fabric_imitation.scenarios.poses import GraspCorners, PoseOnTable
from fabric_imitation.scenarios.schema import Scenario
from fabric_imitation.systems.gripper_contact import (
    CapsulesPenetration,
    GraspCapsules,
)
from pydrake.math import RigidTransform

ON_VIOLATION = ("stop", "count")


@dc.dataclass(frozen=True)
class RefereeRules:
    """Thresholds of the paper's rules (Sec. IV-A) for one task."""

    # Rule 1: tau_c * L < |s1' - s2'| < tau_f * L (L: grasped-edge length).
    tau_c: float
    tau_f: float
    # Rule 2: the angle between each gripper's move and its side, from the
    # far corner to the grasped one, below this [deg].
    tau_d_deg: float
    # Rule 4: the grasped corners stay this far [m] outside the object.
    object_margin: float
    # Bound on each horizontal and the vertical component of one step's move
    # in the object frame [m]: the driver bounds each axis by 3 cm in the
    # frame a method plans in (world for the scripted demo and the baselines'
    # limits, the object frame for the MPC), which in another frame turned
    # about z is at most 3 x sqrt(2) = 4.24 cm.
    max_step: float = 0.045
    # Moves shorter than this [m] have no direction (rule 2 passes them).
    min_move: float = 0.002

    def safety(self) -> SafetyConfig:
        """The rules as a SafetyConfig with none of the controller's
        additions (no hidden-corner hypotheses)."""
        return SafetyConfig(
            tau_c=self.tau_c,
            tau_f=self.tau_f,
            tau_d_deg=self.tau_d_deg,
            min_move=self.min_move,
            object_margin=self.object_margin,
            max_step=self.max_step,
            hidden_corners_hang=False,
        )

    def fingerprint(self) -> str:
        text = json.dumps(dc.asdict(self), sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]


# Per task, from the scripted demo's own figures on the true cloth (its
# largest angle between a move and its side, its largest grasped-edge
# stretch) with a stated allowance: rule 2 at the demo's largest angle
# rounded up to 5 degrees, plus 5; rule 1's upper bound at 1.05 or the
# demo's largest stretch plus 0.03; rule 4 keeps the grasped corners 2 cm
# outside the object, as the demos do. Covering a box, the demo carries the
# near edge over the box and lowers it in front at up to 106 degrees from
# its sides (box and box_big, nominal pose and turned up to 45 degrees);
# hanging a towel, it swings the edge down in front of the plate with the
# towel hanging below the grippers, at up to 152 degrees, stretching the
# edge to 1.049 of its length. docs/benchmark.md gives the command.
REFEREES = {
    "box": RefereeRules(tau_c=0.5, tau_f=1.05, tau_d_deg=115.0, object_margin=0.02),
    "hang": RefereeRules(tau_c=0.5, tau_f=1.08, tau_d_deg=160.0, object_margin=0.02),
}


def TaskReferee(task: str) -> RefereeRules:
    if task not in REFEREES:
        raise InputError(
            f"task {task!r} has no referee; tasks with one: {', '.join(REFEREES)}"
        )
    return REFEREES[task]


def TaskSafetyContext(scenario: Scenario, *, estimated: bool = False) -> SafetyContext:
    """Safety rules for states in the task's frame: the object frame of
    `scenario`, or the world in a scene without an object (the prior scene's
    data collection). `estimated`: the states are the camera's estimates
    (the controller's view), so rule 2 allows for far corners hidden under a
    hanging side (SafetyContext)."""
    has_object = scenario.object.kind != "none"
    lower = np.array(scenario.workspace.lower, float)
    lower[2] = max(lower[2], -scenario.cloth.thickness)
    return SafetyContext(
        edge_length=scenario.cloth.size[0],
        workspace_lower=lower,
        workspace_upper=np.array(scenario.workspace.upper, float),
        object_size=np.array(scenario.object.size, float) if has_object else None,
        object_kind=scenario.object.kind if has_object else "box",
        frame_pose=(
            np.array(PlanarPose.FromDegrees(scenario.object.pose))
            if has_object
            else None
        ),
        far_corners_may_hang=estimated and scenario.safety.hidden_corners_hang,
        side_length=scenario.cloth.size[1],
        hand_spheres=(
            HandSpheres(scenario)
            if estimated and has_object and scenario.safety.hand_shape
            else None
        ),
    )


# Spheres along the hand's capsules at most this fraction of their radius
# apart cover them to within 3.2 % of the radius (Capsule.samples).
HAND_SPHERE_SPACING = 0.5


def HandSpheres(scenario: Scenario) -> np.ndarray:
    """(n, 4) [x, y, z, radius]: spheres covering the scenario's grippers'
    hands around the grasped point (world-aligned; GraspCapsules)."""
    rows = []
    for capsule in GraspCapsules(scenario):
        centres = capsule.samples(HAND_SPHERE_SPACING)
        rows.append(np.column_stack([centres, np.full(len(centres), capsule.radius)]))
    return np.vstack(rows)


def JudgeTransitions(
    rules: RefereeRules,
    scenario: Scenario,
    before_O: np.ndarray,
    action_O: np.ndarray,
    after_O: np.ndarray,
    frame_pose: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """(n,) bool per rule (RULES order), True where transition i (true
    keypoints before (n, M, 3), the executed move (n, 6) and the keypoints
    after, all in the object frame) breaks it; key "any" for any rule.
    `frame_pose`: the object's pose [x, y, yaw_rad] (default: the
    scenario's)."""
    ctx = TaskSafetyContext(scenario)
    if frame_pose is not None:
        ctx = dc.replace(ctx, frame_pose=np.asarray(frame_pose, float))
    n = len(action_O)
    if n == 0:
        return {rule: np.zeros(0, bool) for rule in ("any", *RULES)}
    t = torch.as_tensor
    bad = rule_violations(
        t(np.asarray(before_O), dtype=torch.float64),
        t(np.asarray(action_O), dtype=torch.float64),
        rules.safety(),
        ctx,
        S_next=t(np.asarray(after_O), dtype=torch.float64),
    )
    out = {rule: bad[rule].numpy().astype(bool) for rule in RULES}
    out["any"] = np.any([out[r] for r in RULES], axis=0)
    return out


def FirstBreak(judged: dict[str, np.ndarray]) -> tuple[int, str] | None:
    """(transition index, rule) of the first transition that breaks a rule
    (the first rule in RULES order if several), or None."""
    hits = np.flatnonzero(judged["any"])
    if not len(hits):
        return None
    i = int(hits[0])
    return i, next(r for r in RULES if judged[r][i])


# A trial's start must leave the grippers' hands this far [m] from the task
# object (0: not inside it).
START_CLEARANCE = 0.0


def CheckGrippersClear(scenario: Scenario) -> None:
    """Raises InputError where a gripper's hand, holding its corner at the
    start, would lie within START_CLEARANCE of the task object."""
    if scenario.object.kind == "none":
        return
    X_OW = PoseOnTable(scenario.object.pose).inverse()
    for side, p_W in GraspCorners(scenario).items():
        depth = CapsulesPenetration(
            GraspCapsules(scenario),
            X_OW @ RigidTransform(p_W),
            scenario.object.kind,
            np.array(scenario.object.size, float),
        )
        if depth >= -START_CLEARANCE:
            raise InputError(
                f"the {side} gripper's hand starts {depth * 100:.1f} cm inside "
                f"the object (it must start at least {START_CLEARANCE * 100:g} "
                "cm clear of it)"
            )
