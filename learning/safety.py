"""The safe action set A_V(S) (paper Sec. IV-B), one batched function
shared by data collection and the MPC cost.

Shapes: states S (..., M, 3), actions A (..., 6) = [a_L, a_R], broadcast
against each other. All tensors are torch; `valid_actions_np` wraps numpy.
"""

import dataclasses as dc
import math

import numpy as np
import torch
from fabric_imitation.learning.object_shape import object_signed_distance
from fabric_imitation.learning.state import corner_indices


@dc.dataclass
class SafetyConfig:
    # Rule 1: tau_c * L < |s1' - s2'| < tau_f * L (L: grasped-edge rest length).
    tau_c: float = 0.5
    tau_f: float = 1.05
    # Rule 2: angle(a_L, s1 - s3) and angle(a_R, s2 - s4) below this [deg].
    tau_d_deg: float = 100.0
    # Rule 2's threshold comes from the demo instead: the largest angle the
    # demo's own moves hold with their sides (`demo_direction_angle` on the
    # demo's estimated states, in PrepareImitation) plus
    # tau_d_demo_margin_deg, so that the rule allows what the demo does and
    # little more; tau_d_deg is then not used.
    tau_d_from_demo: bool = True
    tau_d_demo_margin_deg: float = 0.0
    # ... and at most this [deg], whatever the demo's estimated states give:
    # a move nearly against its side folds the cloth back on itself, and
    # the demo's largest angle, a maximum over states estimated under
    # occlusion, can exceed what the demo truly did (the 21 cm rail's demo:
    # 163.0 estimated, 135.0 on its true states). The shipped demos give
    # 90.3-150.3, below it. Evidence for the value: docs/method.md.
    tau_d_max_deg: float = 155.0
    # Moves shorter than this [m] have no direction: rule 2 passes them.
    min_move: float = 0.002
    # Rule 4: grippers stay this far [m] outside the object's box.
    object_margin: float = 0.02
    # The controller's view only: rule 4 also keeps each gripper's hand (its
    # collision shape around the grasped point, SafetyContext.hand_spheres)
    # out of the object's box, not just the grasped point. On: at
    # development seeds 0-2 (90 paired trials, with the tracker) trials
    # ended by a hand-object collision fall from 5 to 0, success 75 -> 78
    # (+3.3 pp, Newcombe 95 % [-5.6, +12.4]; docs/development.md).
    hand_shape: bool = True
    # ... with each sphere of the hand kept this far [m] from the object
    # (rule 4's margin for the hand; the grasped point keeps object_margin).
    # Between two control steps a gripper overshoots its target by a few
    # millimetres, so a hand planned to graze the object touches it. The
    # evidence for the value is in docs/method.md.
    hand_margin: float = 0.01
    # Action bound [m] per axis per step.
    max_step: float = 0.03
    # The controller's view only (states estimated from the camera): judge
    # rule 2 also with the far corners dropped to the surface below them,
    # since a side hanging from a gripper hides its corner and f_R puts it
    # up by the gripper (SafetyContext.far_corners_may_hang). Rule breaks
    # are always scored without it.
    hidden_corners_hang: bool = True
    # ... and, where a grasped corner is higher above the surface under it
    # than the side is long, with the side hanging straight below it: f_R,
    # seeing the towel from above, puts the far corner up by the grippers,
    # where a move down and back looks safe but points far off the true
    # side.

    def __post_init__(self):
        if not 0 < self.tau_c < self.tau_f:
            raise ValueError(
                f"safety.tau_c/tau_f must satisfy 0 < tau_c < tau_f, got "
                f"{self.tau_c}, {self.tau_f}"
            )
        if not 0 < self.tau_d_deg <= 180:
            raise ValueError(
                f"safety.tau_d_deg must be in (0, 180], got {self.tau_d_deg}"
            )
        if not 0 < self.tau_d_max_deg <= 180:
            raise ValueError(
                f"safety.tau_d_max_deg must be in (0, 180], got {self.tau_d_max_deg}"
            )
        if not 0 <= self.tau_d_demo_margin_deg < 90:
            raise ValueError(
                "safety.tau_d_demo_margin_deg must be in [0, 90), got "
                f"{self.tau_d_demo_margin_deg}"
            )
        if self.hand_margin < 0:
            raise ValueError(f"safety.hand_margin must be >= 0, got {self.hand_margin}")
        if self.max_step <= 0:
            raise ValueError(f"safety.max_step must be positive, got {self.max_step}")

    def for_demo(self, demo_states: np.ndarray) -> "SafetyConfig":
        """These rules for imitating the demo whose states (T, M, 3) are
        given: with tau_d_from_demo, rule 2's threshold is the demo's largest
        move-to-side angle plus the margin, at most tau_d_max_deg."""
        if not self.tau_d_from_demo:
            return self
        angle = demo_direction_angle(demo_states, self.min_move)
        return dc.replace(
            self,
            tau_d_deg=min(self.tau_d_max_deg, angle + self.tau_d_demo_margin_deg),
        )


def demo_direction_angle(states: np.ndarray, min_move: float) -> float:
    """The largest angle [deg] the demo holds between a grasped corner's
    move and its side (s1 - s3 for s1, s2 - s4 for s2, in the state the move
    leaves), over moves longer than `min_move` [m]: rule 2's measure of the
    demo itself. Each move's angle is the median of it and its neighbours'
    (three consecutive moves of the same corner), since a frame in which
    f_R misreads a corner spikes one move's angle while the demo's motion
    changes direction smoothly. 0 for a demo without such moves."""
    S = np.asarray(states, dtype=np.float64)
    idx = corner_indices(S.shape[-2])
    largest = 0.0
    for g, f in (("s1", "s3"), ("s2", "s4")):
        move = S[1:, idx[g]] - S[:-1, idx[g]]
        side = S[:-1, idx[g]] - S[:-1, idx[f]]
        n_move, n_side = np.linalg.norm(move, axis=-1), np.linalg.norm(side, axis=-1)
        cos = (move * side).sum(-1) / np.maximum(n_move * n_side, 1e-12)
        angle = np.degrees(np.arccos(cos.clip(-1, 1)))
        angle[(n_move <= min_move) | (n_side == 0)] = np.nan
        for t in range(len(angle)):
            window = angle[max(t - 1, 0) : t + 2]
            if not np.isnan(angle[t]) and (~np.isnan(window)).sum() >= 2:
                largest = max(largest, float(np.nanmedian(window)))
    return largest


@dc.dataclass
class SafetyContext:
    """What the rules need besides the config, in the frame of the states."""

    edge_length: float  # L
    workspace_lower: np.ndarray  # (3,)
    workspace_upper: np.ndarray  # (3,)
    # The task object's bounding box in the states' frame (the object frame
    # O: centred at the origin in x, y, from z = 0 up), or None; and its kind
    # (learning/object_shape.py): rule 4 judges a box or plate by its box
    # grown by the margin, a cylinder or rail by its signed distance. The
    # hidden-corner hypotheses read the bounding box.
    object_size: np.ndarray | None = None
    object_kind: str = "box"
    # Pose [x, y, yaw_rad] of the states' frame in world, where the workspace
    # box is defined (None: the states are in world).
    frame_pose: np.ndarray | None = None
    # States are camera estimates, whose far corners s3, s4 may be hidden
    # under a hanging side: f_R then puts them on the surface it sees, too
    # high. Rule 2 is then also judged with each far corner dropped halfway
    # and all the way to the surface below it (table or object top), and,
    # where a grasped corner is higher above that surface than the side is
    # long, with the side hanging straight below it, so an action passes
    # only if it passes wherever the corner may hang.
    far_corners_may_hang: bool = False
    # Rest length [m] of the sides s1-s3 and s2-s4 (None: edge_length).
    side_length: float | None = None
    # Spheres (n, 4) [x, y, z, radius] covering a gripper's hand, around the
    # grasped point with world-aligned axes: rule 4 also refuses a gripper
    # where one of them enters the object's box (SafetyConfig.hand_shape;
    # None: the grippers are points).
    hand_spheres: np.ndarray | None = None


RULES = ("bounds", "distance", "direction", "workspace", "object")


def rule_violations(
    S: torch.Tensor,
    A: torch.Tensor,
    config: SafetyConfig,
    ctx: SafetyContext,
    S_next: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """Boolean tensors (...) per rule, True where the rule is violated.

    Rule 3 (workspace) is checked on `S_next` when given (the MPC's predicted
    state); otherwise on S with the grasped corners moved by A (data
    collection, before the move is made).
    """
    m = S.shape[-2]
    idx = corner_indices(m)
    a_l, a_r = A[..., :3], A[..., 3:]
    s1, s2 = S[..., idx["s1"], :], S[..., idx["s2"], :]
    s3, s4 = S[..., idx["s3"], :], S[..., idx["s4"], :]
    s1n, s2n = s1 + a_l, s2 + a_r
    out = {}
    out["bounds"] = (A.abs() > config.max_step + 1e-9).any(-1)
    d = (s1n - s2n).norm(dim=-1)
    L = ctx.edge_length
    out["distance"] = (d <= config.tau_c * L) | (d >= config.tau_f * L)
    cos_max = math.cos(math.radians(config.tau_d_deg))

    def bad_direction(a, edge):
        na, ne = a.norm(dim=-1), edge.norm(dim=-1)
        cos = (a * edge).sum(-1) / (na * ne).clamp_min(1e-12)
        return (na > config.min_move) & (cos <= cos_max)

    out["direction"] = bad_direction(a_l, s1 - s3) | bad_direction(a_r, s2 - s4)
    if ctx.far_corners_may_hang:
        floor3, floor4 = _surface_below(s3, ctx), _surface_below(s4, ctx)
        for fraction in (0.5, 1.0):
            s3d = _dropped(s3, fraction, ctx, floor3)
            s4d = _dropped(s4, fraction, ctx, floor4)
            out["direction"] = (
                out["direction"]
                | bad_direction(a_l, s1 - s3d)
                | bad_direction(a_r, s2 - s4d)
            )
        # A side hanging free: its far corner straight below the gripper, so
        # the edge points straight up.
        side = ctx.side_length or ctx.edge_length
        up = torch.tensor([0.0, 0.0, 1.0], dtype=S.dtype)
        for a, g in ((a_l, s1), (a_r, s2)):
            free = g[..., 2] - _dropped(g, 1.0, ctx)[..., 2] >= side
            if free.any():  # rarely: the rollouts' grippers are low
                out["direction"] = out["direction"] | (free & bad_direction(a, up))
    grippers = torch.stack([s1n, s2n], -2)
    out["workspace"] = _outside_workspace(S, A, S_next, grippers, ctx)
    if ctx.object_size is not None:
        half = torch.as_tensor(ctx.object_size, dtype=S.dtype) / 2
        margin = config.object_margin
        if ctx.object_kind in ("box", "plate"):
            inside = (
                (grippers[..., 0].abs() < half[0] + margin)
                & (grippers[..., 1].abs() < half[1] + margin)
                & (grippers[..., 2] < 2 * half[2] + margin)
            )
        else:
            kind, size = ctx.object_kind, ctx.object_size
            inside = object_signed_distance(grippers, kind, size) < margin
        out["object"] = inside.any(-1)
        if ctx.hand_spheres is not None:
            out["object"] = out["object"] | _hand_in_box(
                grippers, ctx, config.hand_margin
            )
    else:
        out["object"] = torch.zeros_like(out["bounds"])
    return out


def _hand_in_box(
    grippers: torch.Tensor, ctx: SafetyContext, margin: float = 0.0
) -> torch.Tensor:
    """(...,) True where a sphere of either gripper's hand (ctx.hand_spheres,
    world-aligned, turned into the states' frame) comes closer than `margin`
    [m] to the object (the states' frame: centred in x and y, from z = 0
    up)."""
    spheres = torch.as_tensor(ctx.hand_spheres, dtype=grippers.dtype)
    offsets, radius = spheres[:, :3], spheres[:, 3]
    if ctx.frame_pose is not None:
        c, s = math.cos(float(ctx.frame_pose[2])), math.sin(float(ctx.frame_pose[2]))
        # World-aligned offsets into the frame turned by yaw: R(yaw)^T v.
        offsets = torch.stack(
            [
                c * offsets[:, 0] + s * offsets[:, 1],
                -s * offsets[:, 0] + c * offsets[:, 1],
                offsets[:, 2],
            ],
            -1,
        )
    points = grippers[..., None, :] + offsets  # (..., 2, n, 3)
    distance = object_signed_distance(points, ctx.object_kind, ctx.object_size)
    return (distance < radius + margin).any(-1).any(-1)


def _outside_workspace(S, A, S_next, grippers, ctx: SafetyContext) -> torch.Tensor:
    """Rule 3: any point (the state's keypoints with the grasped corners
    moved, or the predicted state and the gripper targets) outside the
    workspace box, or a gripper below the table top."""
    idx = corner_indices(S.shape[-2])
    lo = torch.as_tensor(ctx.workspace_lower, dtype=S.dtype)
    hi = torch.as_tensor(ctx.workspace_upper, dtype=S.dtype)
    if S_next is None:
        moved = (
            S.clone()
            if S.shape[:-2] == A.shape[:-1]
            else S.expand(*A.shape[:-1], *S.shape[-2:]).clone()
        )
        moved[..., idx["s1"], :] = grippers[..., 0, :]
        moved[..., idx["s2"], :] = grippers[..., 1, :]
        points = moved  # the grasped corners are the gripper targets
    else:
        # The predicted state and the gripper targets themselves.
        points = torch.cat(
            [S_next, grippers.expand(*S_next.shape[:-2], *grippers.shape[-2:])], -2
        )
    px, py, pz = points[..., 0], points[..., 1], points[..., 2]
    if ctx.frame_pose is not None:
        x, y, yaw = (float(v) for v in ctx.frame_pose)
        c, s = math.cos(yaw), math.sin(yaw)
        px, py = c * px - s * py + x, s * px + c * py + y
    outside = (
        (px < lo[0])
        | (px > hi[0])
        | (py < lo[1])
        | (py > hi[1])
        | (pz < lo[2])
        | (pz > hi[2])
    ).any(-1)
    # Grippers never go below the table top.
    return outside | (grippers[..., 2] < 0.0).any(-1)


def _surface_below(p: torch.Tensor, ctx: SafetyContext) -> torch.Tensor:
    """Height (...) of the surface under points p (..., 3): the object's top
    inside its footprint, else the table (z = 0); frame: the object frame."""
    floor = torch.zeros_like(p[..., 2])
    if ctx.object_size is not None:
        half = torch.as_tensor(ctx.object_size, dtype=p.dtype) / 2
        over = (p[..., 0].abs() < half[0]) & (p[..., 1].abs() < half[1])
        floor = torch.where(over, 2 * half[2], floor)
    return floor


def _dropped(
    p: torch.Tensor,
    fraction: float,
    ctx: SafetyContext,
    floor: torch.Tensor | None = None,
) -> torch.Tensor:
    """Points p (..., 3) moved down by `fraction` of their height above the
    surface under them (`_surface_below`, or `floor` where given)."""
    if floor is None:
        floor = _surface_below(p, ctx)
    z = p[..., 2] - fraction * (p[..., 2] - floor).clamp_min(0.0)
    return torch.cat([p[..., :2], z[..., None]], -1)


def direction_angles(S: torch.Tensor, A: torch.Tensor, min_move: float) -> torch.Tensor:
    """(..., 2) rule 2's measure [deg]: the angle of a_L with s1 - s3 and of
    a_R with s2 - s4 in state S (..., M, 3), 0 for a move shorter than
    `min_move` [m] (it has no direction)."""
    idx = corner_indices(S.shape[-2])
    out = []
    for a, g, f in ((A[..., :3], "s1", "s3"), (A[..., 3:], "s2", "s4")):
        side = S[..., idx[g], :] - S[..., idx[f], :]
        na, ns = a.norm(dim=-1), side.norm(dim=-1)
        cos = (a * side).sum(-1) / (na * ns).clamp_min(1e-12)
        angle = torch.rad2deg(torch.acos(cos.clamp(-1.0, 1.0)))
        out.append(torch.where(na > min_move, angle, torch.zeros_like(angle)))
    return torch.stack(out, -1)


def valid_actions(
    S: torch.Tensor,
    A: torch.Tensor,
    config: SafetyConfig,
    ctx: SafetyContext,
    S_next: torch.Tensor | None = None,
) -> torch.Tensor:
    """(...) True where the action A is valid in state S (all rules hold)."""
    bad = rule_violations(S, A, config, ctx, S_next)
    out = torch.zeros_like(bad["bounds"])
    for v in bad.values():
        out = out | v
    return ~out


def valid_actions_np(
    S, A, config: SafetyConfig, ctx: SafetyContext, S_next=None
) -> np.ndarray:
    t = torch.as_tensor
    return valid_actions(
        t(np.array(S, dtype=np.float64)),
        t(np.asarray(A, dtype=np.float64)),
        config,
        ctx,
        None if S_next is None else t(np.asarray(S_next, dtype=np.float64)),
    ).numpy()
