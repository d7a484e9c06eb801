"""Demonstration learning (paper Section IV-C): the
state-alignment reward R_E = J - w_P D_P - w_N D_N and the termination
classifier, built from one demo's states S_E^1..T in the object frame.

Indices are 0-based here: J in 0..T-1, the subgoal is S_E[min(J + 1, T - 1)],
the final state S_E[T - 1].
"""

import copy
import dataclasses as dc
import hashlib
import math
import platform
import time
from pathlib import Path

import numpy as np
import torch
from fabric_imitation.learning import models as models_module
from fabric_imitation.learning.cache import cache_dir, read_torch, write_torch
from fabric_imitation.learning.models import Mlp
from fabric_imitation.learning.polygon import iou_pairs


@dc.dataclass
class RewardConfig:
    # Weight of the positive distance D_P to the subgoal (per metre).
    w_p: float = 50.0
    # Weight of rotation [rad] against translation [m] inside D_P.
    w_r: float = 0.1
    # Weight of the negative (overshoot) distance D_N.
    w_n: float = 50.0
    # Termination: IoU with the last demo state above this, and J >= T - 1 -
    # done_progress_slack.
    tau_i: float = 0.75
    # Termination's progress test passes from J = T - 1 - this on (0: J =
    # T - 1, the paper's). J, the argmax over demo states, moves back and
    # forth by one state where consecutive demo states differ by less than
    # the estimate's error.
    done_progress_slack: int = 0
    # Progress score = IoU - this [1/m] x mean 3-D keypoint distance. The
    # paper's top-down IoU alone cannot tell a cloth lifted or lowered in place
    # from one at another height (the hang demo lowers 32 cm straight down), so
    # the distance breaks such ties; 0 gives the paper's J.
    progress_distance_weight: float = 2.0
    # f_A training: steps, batch, learning rate.
    registration_steps: int = 1500
    registration_batch: int = 256
    registration_lr: float = 2e-3
    # f_A's sources, centred on the demo, also turned about their centroids
    # by a random yaw of up to this [deg] and moved by up to this [m] in x
    # and y; 0, 0: centred only.
    source_yaw_deg: float = 0.0
    source_shift: float = 0.0
    seed: int = 0

    def __post_init__(self):
        for name in ("w_p", "w_r", "w_n"):
            if getattr(self, name) < 0:
                raise ValueError(f"reward.{name} must be non-negative")
        if not 0 < self.tau_i <= 1:
            raise ValueError(f"reward.tau_i must be in (0, 1], got {self.tau_i}")
        if self.done_progress_slack < 0:
            raise ValueError(
                "reward.done_progress_slack must be non-negative, got "
                f"{self.done_progress_slack}"
            )
        if not 0 <= self.source_yaw_deg <= 180:
            raise ValueError(
                f"reward.source_yaw_deg must be in [0, 180], got {self.source_yaw_deg}"
            )
        if self.source_shift < 0:
            raise ValueError(
                f"reward.source_shift must be non-negative, got {self.source_shift}"
            )


def euler_to_matrix(e: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (..., 3, 3) from roll-pitch-yaw angles (..., 3)."""
    r, p, y = e[..., 0], e[..., 1], e[..., 2]
    cr, sr, cp, sp, cy, sy = r.cos(), r.sin(), p.cos(), p.sin(), y.cos(), y.sin()
    return torch.stack(
        [
            torch.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
            torch.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
            torch.stack([-sp, cp * sr, cp * cr], -1),
        ],
        -2,
    )


class Registration:
    """f_A(S, S_E) -> (R as Euler angles, T) with R S + T ~ S_E (MLP)."""

    def __init__(self, num_keypoints: int, scale: float = 0.2):
        self.net = Mlp(6 * num_keypoints, 6)
        self.scale = scale  # metres: states are divided by it at the input

    # Rows per forward pass outside training: the hidden activations of a
    # few thousand rows leave the CPU's cache, and chunks of 512 run about
    # twice as fast (learning/models.py's MLP, one thread).
    CHUNK = 512

    def __call__(self, S: torch.Tensor, S_E: torch.Tensor):
        x = torch.cat([S.flatten(-2), S_E.flatten(-2)], -1) / self.scale
        if torch.is_grad_enabled() or x[..., 0].numel() <= self.CHUNK:
            out = self.net(x)
        else:
            rows = x.reshape(-1, x.shape[-1]).split(self.CHUNK)
            out = torch.cat([self.net(c) for c in rows]).reshape(*x.shape[:-1], -1)
        return out[..., :3], out[..., 3:] * self.scale

    def align(self, S, S_E):
        e, T = self(S, S_E)
        return S @ euler_to_matrix(e).transpose(-1, -2) + T[..., None, :], e, T

    def fit(self, sources: torch.Tensor, targets: torch.Tensor, cfg: RewardConfig):
        """Trains on random (source, target) pairs, minimising the alignment
        error |R S + T - S_E|^2."""
        gen = torch.Generator().manual_seed(cfg.seed)
        opt = torch.optim.Adam(self.net.parameters(), lr=cfg.registration_lr)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, cfg.registration_steps)
        losses = []
        for _ in range(cfg.registration_steps):
            i = torch.randint(len(sources), (cfg.registration_batch,), generator=gen)
            j = torch.randint(len(targets), (cfg.registration_batch,), generator=gen)
            aligned, _, _ = self.align(sources[i], targets[j])
            loss = ((aligned - targets[j]) ** 2).sum(-1).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            losses.append(loss.item())
        self.net.eval()
        return losses


def centred_states(
    S: torch.Tensor,
    around: torch.Tensor,
    yaw_deg: float = 0.0,
    shift: float = 0.0,
    gen: torch.Generator | None = None,
) -> torch.Tensor:
    """Prior states (n, M, 3) moved on the table so that each one's centroid
    is at `around` (x, y): the demo's centroid, where f_A's targets are.
    Where `yaw_deg` or `shift` is above 0, each is also turned about its
    centroid by a yaw drawn uniformly from [-yaw_deg, yaw_deg] and moved by
    a draw from [-shift, shift] in x and in y (both drawn with `gen`)."""
    n = len(S)
    centre = S[..., :2].mean(-2, keepdim=True)
    flat = torch.cat([centre, torch.zeros_like(centre[..., :1])], -1)
    if yaw_deg <= 0 and shift <= 0:
        target = torch.cat([around[:2].expand(n, 1, 2), torch.zeros(n, 1, 1)], -1)
        return (S - flat) + target
    yaw = (torch.rand(n, generator=gen) * 2 - 1) * math.radians(yaw_deg)
    c, s = yaw.cos(), yaw.sin()
    z, o = torch.zeros_like(c), torch.ones_like(c)
    R = torch.stack(
        [
            torch.stack([c, -s, z], -1),
            torch.stack([s, c, z], -1),
            torch.stack([z, z, o], -1),
        ],
        -2,
    )
    moved = (torch.rand(n, 1, 2, generator=gen) * 2 - 1) * shift
    target = torch.cat([around[:2] + moved, torch.zeros(n, 1, 1)], -1)
    return (S - flat) @ R.transpose(-1, -2) + target


class DemoModel:
    """The demo's states and the reward/termination built on them. Batched:
    every method takes states (..., M, 3) in the object frame."""

    def __init__(
        self, states: np.ndarray, registration: Registration, config: RewardConfig
    ):
        self.states = torch.as_tensor(np.asarray(states), dtype=torch.float32)
        self.T = len(self.states)
        self.f_A = registration
        self.config = config
        self.polygons = self.states[..., :2]
        self.centres = self.polygons.mean(-2)

    def similarity(self, S: torch.Tensor, window: tuple[int, int] | None = None):
        """IoU (..., W) of the top-down polygons of S with demo states
        lo..hi-1 (default all)."""
        lo, hi = window or (0, self.T)
        lead = S.shape[:-2]
        A = S[..., :2].reshape(-1, *S.shape[-2:-1], 2)
        return iou_pairs(A, self.polygons[lo:hi]).reshape(*lead, hi - lo)

    def progress(self, S: torch.Tensor, window: tuple[int, int] | None = None):
        """J (...): index of the most similar demo state by IoU of the top-down
        keypoint polygons; by nearest polygon centre where S overlaps none."""
        lo, hi = window or (0, self.T)
        sim = self.similarity(S, (lo, hi))
        score = sim
        cfg = self.config
        if cfg.progress_distance_weight > 0:
            # Mean keypoint distance (..., W) to each demo state.
            d = (S[..., None, :, :] - self.states[lo:hi]).norm(dim=-1)
            score = score - cfg.progress_distance_weight * d.mean(-1)
        _, j = score.max(-1)
        best_iou = sim.max(-1).values
        centre = S[..., :2].mean(-2)
        dist = (centre[..., None, :] - self.centres[lo:hi]).norm(dim=-1)
        j = torch.where(best_iou > 0, j, dist.argmin(-1))
        return j + lo, best_iou

    @torch.no_grad()
    def reward(self, S: torch.Tensor, window: tuple[int, int] | None = None):
        """R_E (...), and J (...)."""
        S = torch.as_tensor(S, dtype=torch.float32)
        cfg = self.config
        J, _ = self.progress(S, window)
        sub = self.states[(J + 1).clamp(max=self.T - 1)]
        e, T = self.f_A(S, sub)
        d_p = T.norm(dim=-1) + cfg.w_r * e.norm(dim=-1)
        last = self.states[-1]
        prev = self.states[max(self.T - 2, 0)]
        d_last = (S - last).norm(dim=-1).mean(-1)
        d_prev = (S - prev).norm(dim=-1).mean(-1)
        d_n = torch.where(
            (J >= self.T - 2) & (d_last < d_prev), d_last, torch.zeros_like(d_last)
        )
        return J.float() - cfg.w_p * d_p - cfg.w_n * d_n, J

    @torch.no_grad()
    def done(self, S: torch.Tensor) -> torch.Tensor:
        """Termination classifier: IoU with S_E^T above tau_I and J >= T - 1
        - `done_progress_slack` (J = T - 1 with the paper's slack 0)."""
        S = torch.as_tensor(S, dtype=torch.float32)
        progress, _ = self.progress(S)
        last_iou = self.similarity(S, (self.T - 1, self.T))[..., 0]
        first = self.T - 1 - self.config.done_progress_slack
        return (last_iou > self.config.tau_i) & (progress >= first)


# f_A's training inputs besides the states (RewardConfig fields).
REGISTRATION_FIELDS = (
    "registration_steps",
    "registration_batch",
    "registration_lr",
    "source_yaw_deg",
    "source_shift",
    "seed",
)


def registration_key(demo_states, prior_states, cfg: RewardConfig) -> str:
    """Checksum of everything f_A's training depends on: the demo's and the
    prior's states, the training settings, the code that trains it, the
    torch version, its thread count and the CPU's instruction set (both
    change the rounding of the training's sums): a cached f_A is what
    training here and now would give."""
    h = hashlib.sha256()
    for states in (demo_states, prior_states):
        a = np.ascontiguousarray(np.asarray(states, dtype=np.float32))
        h.update(str(a.shape).encode() + a.tobytes())
    h.update(repr([getattr(cfg, f) for f in REGISTRATION_FIELDS]).encode())
    for module in (__file__, models_module.__file__):
        h.update(Path(module).read_bytes())
    h.update(
        " ".join(
            [
                torch.__version__,
                str(torch.get_num_threads()),
                torch.backends.cpu.get_cpu_capability(),
                platform.machine(),
            ]
        ).encode()
    )
    return h.hexdigest()[:24]


def learn_from_demo(
    demo_states: np.ndarray,
    prior_states: np.ndarray,
    config: RewardConfig | None = None,
    *,
    cache: bool = True,
) -> tuple[DemoModel, dict]:
    """Builds the demo model: trains f_A with prior states (centred on the
    demo's centroid) as sources and the demo's states as targets. Returns
    the model and a summary (training time, final alignment error, whether
    f_A came from the cache).

    With `cache`, f_A's weights are kept in the project's cache
    (learning/cache.py) under `RegistrationKey`, so the same demo and
    priors are registered once per machine; a cached f_A is the trained one,
    weight for weight."""
    cfg = config or RewardConfig()
    # f_A's initial weights come from torch's global stream, seeded here;
    # a cached f_A leaves that stream where training would.
    torch.manual_seed(cfg.seed)
    t0 = time.perf_counter()
    targets = torch.as_tensor(np.asarray(demo_states), dtype=torch.float32)
    f_A = Registration(targets.shape[-2])
    path = None
    if cache:
        key = registration_key(demo_states, prior_states, cfg)
        path = cache_dir() / f"registration-{key}.pt"
        cached = _cached_registration(path, f_A)
        if cached is not None:
            f_A, final_loss = cached
            return DemoModel(targets.numpy(), f_A, cfg), {
                "registration_seconds": round(time.perf_counter() - t0, 2),
                "registration_final_loss": final_loss,
                "registration_cached": True,
            }
    around = targets[..., :2].reshape(-1, 2).mean(0)
    sources = centred_states(
        torch.as_tensor(np.asarray(prior_states), dtype=torch.float32),
        around,
        cfg.source_yaw_deg,
        cfg.source_shift,
        torch.Generator().manual_seed(cfg.seed),
    )
    losses = f_A.fit(sources, targets, cfg)
    final_loss = round(float(np.mean(losses[-50:])), 6)
    if path is not None:
        write_torch(path, {"net": f_A.net.state_dict(), "final_loss": final_loss})
    model = DemoModel(targets.numpy(), f_A, cfg)
    return model, {
        "registration_seconds": round(time.perf_counter() - t0, 2),
        "registration_final_loss": final_loss,
        "registration_cached": False,
    }


def _cached_registration(
    path: Path, fresh: Registration
) -> tuple[Registration, float] | None:
    """(f_A with the weights cached at `path`, its final training loss), or
    None where the entry is missing or does not fit; `fresh` is left as it
    was either way."""
    saved = read_torch(path)
    if saved is None or not isinstance(saved.get("final_loss"), float):
        return None
    f_A = copy.deepcopy(fresh)
    try:
        f_A.net.load_state_dict(saved["net"])
    except (KeyError, RuntimeError, TypeError, AttributeError):
        return None
    f_A.net.eval()
    return f_A, saved["final_loss"]
