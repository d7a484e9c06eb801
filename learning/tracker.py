"""A keypoint tracker: f_R's reading of each frame fused with f_D's
prediction from the previous estimate and the grippers' measured move.

The paper names tracking the manipulated object through the whole
manipulation as the remedy for occlusion (Sec. VI). Each keypoint k carries
an estimate x_k and a variance v_k per axis (m^2). Per control step:

    predict   x^- = f_D(x, a),            v^- = v + q^2
    measure   z_k = f_R's keypoint,       r_k = (sigma_0 + c * spread_k^2)^2
    fuse      g_k = v^-_k / (v^-_k + r_k), x_k = x^-_k + g_k (z_k - x^-_k),
              v_k = (1 - g_k) v^-_k

where a is the grippers' displacement since the last frame (the robot
measures it), spread_k f_R's heatmap standard deviation [px]
(KeypointNet.locate), and q f_D's one-step error (TrackerConfig says which
statistic each is). Variances are kept per axis (M, 3); with
`measurement_vertical_base` and `measurement_vertical_per_px2` set, r_k is
f_R's horizontal error in x and y and its vertical error in z (a corner
hidden under the cloth is read on the surface above it: mostly a height
error), otherwise the same in all three. The grasped corners s1, s2 are where the
grippers hold them. Optionally (off by default), a predicted keypoint inside
the task object is put on the object's nearest face, as the cloth simulator
does for held particles, since f_D learned no contact.

`fabric-imitate bench tracker --json` fits both errors on the shipped demos'
frames against the simulator's true keypoints, for the shipped priors, and
reports how far f_R alone and the tracker are from them (on the same frames:
in-sample figures).
"""

import dataclasses as dc
import math
from collections.abc import Callable

import numpy as np
import torch
from fabric_imitation.learning.state import (
    corner_indices,
    object_to_world,
    world_to_object,
)


@dc.dataclass
class TrackerConfig:
    # Off: each control step's keypoints are f_R's reading of that frame
    # alone (the grasped corners from the grippers). On: at development pose
    # seeds 0-2 (90 paired trials, box, hang, box_big) ours succeeds 11.1 pp
    # more often, Newcombe 95 % [+1.3, +20.9] (docs/development.md).
    enabled: bool = True
    # f_R's mean error [m] for a keypoint whose heatmap spread is s [px]:
    # measurement_base + measurement_per_px2 * s^2, the least-squares fit
    # over the shipped demos' frames for the shipped priors (`bench
    # tracker`). A sharp heatmap (3 px) is about 0.8 cm off, a diffuse one
    # (25 px), a corner f_R cannot see, about 17 cm.
    measurement_base: float = 0.006
    measurement_per_px2: float = 2.7e-4
    # f_D's one-step error [m] (the process noise): the root mean square of
    # its error over the shipped demos' keypoints other than the grasped
    # corners, predicted from the true state and move, for the shipped
    # priors and the 0.2 s control step (`bench tracker`). Its mean, 0.0175,
    # trusts f_D more: on the same frames the tracker then strays up to
    # 1.2 cm from f_R's sharp readings (spread <= 4 px) on hang, against
    # 0.6 cm, and is further off on box_big (1.74 cm against f_R's 1.57).
    process_noise: float = 0.026
    # f_R's vertical error [m] for spread s [px]: measurement_vertical_base +
    # measurement_vertical_per_px2 * s^2, where both are given; then
    # measurement_base and measurement_per_px2 are its horizontal error (the
    # error in x and in y, each axis a sample of the fit), each fitted the
    # same way (`bench tracker`).
    # None: one error for all three axes (the 3-D error's fit above).
    measurement_vertical_base: float | None = None
    measurement_vertical_per_px2: float | None = None

    # The controller's grasped corners s1, s2 are the measured gripper
    # positions (where the grippers hold them) instead of f_R's reading of
    # the frame; the grippers' measured move drives the prediction either
    # way. False: s1, s2 are estimated like every other keypoint (the
    # paper's states come from f_R alone).
    grasped_from_grippers: bool = True

    # Put predicted keypoints that lie inside the task object on its
    # nearest face (f_D learned no contact). Off: on the shipped demos'
    # frames the mean errors with and without it agree to 0.01 cm (`bench
    # tracker`), and in the loop, on against off over the five tasks and
    # two rail sizes at development seeds 39-40 (140 pairs), +2.1 pp,
    # Newcombe 95 % [-3.4, +7.8] (docs/method.md).
    object_projection: bool = False

    # The demo's grasped-corner track, which stands in for the grippers the
    # video does not measure (`running_median`): each frame's s1, s2 the
    # median of f_R's readings over this many consecutive frames (odd; 1:
    # each frame's own reading). A hand moves smoothly, so a corner f_R
    # misreads in one frame (the hang demo's left corner at frame 15, read
    # 20 cm below the grippers) is dropped instead of becoming a subgoal.
    demo_grasped_median: int = 1

    def __post_init__(self):
        if self.demo_grasped_median < 1 or self.demo_grasped_median % 2 == 0:
            raise ValueError(
                "tracker.demo_grasped_median must be an odd number of frames "
                f">= 1, got {self.demo_grasped_median}"
            )
        for name in ("measurement_base", "process_noise"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(
                    f"tracker.{name} must be positive and finite, got {value}"
                )
        vertical = (self.measurement_vertical_base, self.measurement_vertical_per_px2)
        if (vertical[0] is None) != (vertical[1] is None):
            raise ValueError(
                "tracker.measurement_vertical_base and "
                "tracker.measurement_vertical_per_px2 go together: give both or "
                "neither"
            )
        if vertical[0] is not None and not (
            math.isfinite(vertical[0]) and vertical[0] > 0
        ):
            raise ValueError(
                "tracker.measurement_vertical_base must be positive and finite, "
                f"got {vertical[0]}"
            )
        if vertical[1] is not None and not (
            math.isfinite(vertical[1]) and vertical[1] >= 0
        ):
            raise ValueError(
                "tracker.measurement_vertical_per_px2 must be >= 0 and finite, "
                f"got {vertical[1]}"
            )
        if not (
            math.isfinite(self.measurement_per_px2) and self.measurement_per_px2 >= 0
        ):
            raise ValueError(
                "tracker.measurement_per_px2 must be >= 0 and finite, got "
                f"{self.measurement_per_px2}"
            )


def measurement_sigma(spread: np.ndarray, config: TrackerConfig) -> np.ndarray:
    """f_R's error [m] for heatmap spreads [px] (TrackerConfig)."""
    spread = np.asarray(spread, dtype=np.float64)
    return config.measurement_base + config.measurement_per_px2 * spread**2


def measurement_sigmas(spread: np.ndarray, config: TrackerConfig) -> np.ndarray:
    """f_R's error [m] per axis (..., 3) for heatmap spreads (...) [px]: the
    horizontal error in x and y and the vertical in z where the config has a
    vertical model, else `measurement_sigma` in all three."""
    sigma = measurement_sigma(spread, config)
    if config.measurement_vertical_base is None:
        return np.repeat(sigma[..., None], 3, -1)
    spread = np.asarray(spread, dtype=np.float64)
    vertical = (
        config.measurement_vertical_base
        + config.measurement_vertical_per_px2 * spread**2
    )
    return np.stack([sigma, sigma, vertical], -1)


# [m] the least base an error fit returns: f_R's error with the sharpest
# heatmap is not below a millimetre (the cloth's particles are 2 cm apart).
MIN_MEASUREMENT_BASE = 0.001


def fit_measurement_model(spread: np.ndarray, error: np.ndarray) -> tuple[float, float]:
    """Least-squares (base, per_px2) of error ~ base + per_px2 * spread^2 over
    paired samples of f_R's spread [px] and its error [m]. Where the free fit's
    base is below MIN_MEASUREMENT_BASE (f_R's vertical error with a sharp
    heatmap is about zero), the base is held there and per_px2 fitted alone."""
    spread = np.asarray(spread, dtype=np.float64).ravel()
    error = np.asarray(error, dtype=np.float64).ravel()
    if spread.shape != error.shape or spread.size < 2:
        raise ValueError("need at least two paired spreads and errors")
    X = np.stack([np.ones_like(spread), spread**2], 1)
    (base, per_px2), *_ = np.linalg.lstsq(X, error, rcond=None)
    if base < MIN_MEASUREMENT_BASE:
        base = MIN_MEASUREMENT_BASE
        s2 = spread**2
        per_px2 = (s2 * (error - base)).sum() / max((s2 * s2).sum(), 1e-30)
        per_px2 = max(0.0, float(per_px2))
    return float(base), float(per_px2)


def project_out_of_box(p: np.ndarray, size: np.ndarray | list[float]) -> np.ndarray:
    """Points (..., 3) in the object frame (the box centred at the origin in
    x, y, from z = 0 up to size[2]) moved from inside the box to its nearest
    face other than the bottom; points outside stay."""
    p = np.array(p, dtype=np.float64, copy=True)
    half = np.array([size[0] / 2, size[1] / 2])
    height = float(size[2])
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    inside = (np.abs(x) < half[0]) & (np.abs(y) < half[1]) & (z < height) & (z > 0)
    if not inside.any():
        return p
    # Distances to the faces: -x, +x, -y, +y, top.
    d = np.stack([x + half[0], half[0] - x, y + half[1], half[1] - y, height - z], -1)
    face = d.argmin(-1)
    q = p[inside]
    f = face[inside]
    q[f == 0, 0] = -half[0]
    q[f == 1, 0] = half[0]
    q[f == 2, 1] = -half[1]
    q[f == 3, 1] = half[1]
    q[f == 4, 2] = height
    p[inside] = q
    return p


class KeypointTracker:
    """Fuses f_R's per-frame keypoints with f_D's prediction (module doc).

    Holds no state of its own: `step` maps the previous estimate and
    variance to the next, so a Drake system can keep them in its context.
    States are (M, 3) in one frame throughout (the estimator uses the task
    object's frame); f_D is invariant to where that frame lies on the table.

    Args:
        forward: f_D, ``forward(S (B, M, 3), A (B, 6)) -> (B, M, 3)``
            (Priors.forward).
        num_keypoints: M.
        config: the error model.
        object_size: the task object as a box in the states' frame (centred
            at the origin in x, y, from z = 0 up), or None.
    """

    def __init__(
        self,
        *,
        forward: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
        num_keypoints: int,
        config: TrackerConfig,
        object_size: np.ndarray | list[float] | None = None,
    ):
        self._forward = forward
        self._m = num_keypoints
        self.config = config
        self._object_size = None if object_size is None else np.asarray(object_size)
        idx = corner_indices(num_keypoints)
        self._grasped = [idx["s1"], idx["s2"]]

    @property
    def num_keypoints(self) -> int:
        return self._m

    def step(
        self,
        previous: tuple[np.ndarray, np.ndarray] | None,
        measured: np.ndarray,
        spread: np.ndarray,
        *,
        action: np.ndarray | None = None,
        grasped: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """One frame. ``previous``: the last (estimate (M, 3), variance (M, 3)),
        or None at the first frame; ``measured`` (M, 3): f_R's keypoints,
        ``spread`` (M,): their heatmap spreads [px]; ``action`` (6,): the
        grippers' move since the previous frame (None: no prediction, f_R's
        reading stands); ``grasped`` (2, 3): where the grippers hold s1 and
        s2, or None. Returns the new (estimate (M, 3), variance (M, 3) per
        axis); a previous variance (M,) is taken as the same on each axis."""
        measured = np.asarray(measured, dtype=np.float64)
        if measured.shape != (self._m, 3):
            raise ValueError(f"keypoints must be ({self._m}, 3), got {measured.shape}")
        if np.shape(spread) != (self._m,):
            raise ValueError(f"spreads must be ({self._m},), got {np.shape(spread)}")
        r = measurement_sigmas(spread, self.config) ** 2
        if previous is not None and not (
            np.all(np.isfinite(previous[0])) and np.all(np.isfinite(previous[1]))
        ):
            previous = None  # a broken estimate starts again from f_R
        if previous is None or action is None:
            x, v = measured.copy(), r
        else:
            estimate, variance = previous
            x = self._predict(estimate, np.asarray(action, dtype=np.float64))
            v = np.asarray(variance, dtype=np.float64)
            if v.ndim == 1:
                v = np.repeat(v[:, None], 3, -1)
            v = v + self.config.process_noise**2
            gain = v / (v + r)
            x = x + gain * (measured - x)
            v = (1.0 - gain) * v
        if grasped is not None:
            x[self._grasped] = np.asarray(grasped, dtype=np.float64).reshape(2, 3)
            v = v.copy()
            v[self._grasped] = 0.0
        return x, v

    def _predict(self, x: np.ndarray, action: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            pred = self._forward(
                torch.as_tensor(np.asarray(x)[None], dtype=torch.float32),
                torch.as_tensor(action.reshape(1, 6), dtype=torch.float32),
            )
        pred = np.asarray(pred, dtype=np.float64)[0]
        if self.config.object_projection and self._object_size is not None:
            pred = project_out_of_box(pred, self._object_size)
        return pred


def running_median(track: np.ndarray, frames: int) -> np.ndarray:
    """Each row of ``track`` (T, ...) replaced by the median of the rows
    around it, per coordinate: ``frames`` rows (odd) centred on it, fewer
    near the ends, where the window shrinks to stay centred (the first and
    last rows are kept). 1 returns a copy."""
    track = np.asarray(track, dtype=np.float64)
    out = track.copy()
    T = len(track)
    for t in range(T):
        half = min(frames // 2, t, T - 1 - t)
        if half > 0:
            out[t] = np.median(track[t - half : t + half + 1], axis=0)
    return out


def track_states(
    tracker: KeypointTracker,
    measured: np.ndarray,
    spread: np.ndarray,
    grasped: np.ndarray,
) -> np.ndarray:
    """Tracks a recorded sequence in one frame: f_R's keypoints ``measured``
    (T, M, 3) with their spreads (T, M), the grasped corners ``grasped``
    (T, 2, 3), each frame's move the difference of consecutive ones.
    Returns the tracked keypoints (T, M, 3)."""
    out, state = [], None
    for t in range(len(measured)):
        action = None if t == 0 else (grasped[t] - grasped[t - 1]).ravel()
        state = tracker.step(
            state, measured[t], spread[t], action=action, grasped=grasped[t]
        )
        out.append(state[0])
    return np.array(out)


def track_frames(
    priors,
    masks: np.ndarray,
    depths: np.ndarray,
    grasped_W: np.ndarray,
    config: TrackerConfig,
    *,
    object_pose: np.ndarray | None = None,
    object_size: np.ndarray | list[float] | None = None,
) -> dict:
    """Tracks a recorded episode: ``masks``, ``depths`` (T, H, W), the
    grippers' positions ``grasped_W`` (T, 2, 3) in world. ``priors``:
    Priors (f_R's ``keypoints_and_spread``, f_D's ``forward``). Returns
    world keypoints of f_R alone (``measured``) and tracked (``tracked``),
    (T, M, 3), and f_R's spreads (``spread``, (T, M)). ``object_pose`` [x,
    y, yaw_rad] and ``object_size`` give the object for the projection (the
    tracker runs in the object's frame)."""
    measured, spread = priors.keypoints_and_spread(masks, depths)
    pose = np.zeros(3) if object_pose is None else np.asarray(object_pose)
    tracker = KeypointTracker(
        forward=priors.forward,
        num_keypoints=priors.num_keypoints,
        config=config,
        object_size=object_size,
    )
    T = len(measured)
    grasped_O = world_to_object(grasped_W.reshape(-1, 3), pose).reshape(T, 2, 3)
    measured_O = world_to_object(measured.reshape(-1, 3), pose).reshape(measured.shape)
    tracked_O = track_states(tracker, measured_O, spread, grasped_O)
    tracked = object_to_world(tracked_O.reshape(-1, 3), pose).reshape(measured.shape)
    return {"measured": measured, "tracked": tracked, "spread": spread}
