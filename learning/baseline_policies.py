"""The baselines at run time (paper Table I): what each one does, each
control step, with its networks (learning/baselines.py), the demo's states
(f_R on its frames) and, for TCN, the priors' forward model f_D.

Every method may use the shared prior dataset and what is learned from it
(f_R, f_D); what the baselines lack is the paper's contribution: no safe
action set, no hidden-corner hypotheses, no action prior (f_I or the grasped
corners), no state-alignment reward. Their moves pass only the robot
driver's limits (learning/limits.py: +-max_step per axis, the gripper
targets inside the workspace box and above the table), as every method's do.

- **Zero** (`ZeroFollower`, Pathak et al. 2018): subgoal j starts at demo
  frame 1; each step, while the goal recognizer says the state S has reached
  demo frame j (r(S, S_E[j]) > `reached_probability`), j advances; the move
  is the goal-conditioned inverse model's pi(S, S_E[j]). After `max_tries`
  steps on one subgoal the follower moves on anyway (so it cannot stall);
  the episode ends when the recognizer has passed the demo's last frame (or
  the last subgoal ran out of tries).
- **CFM** (`CfmPlanner`, Yan et al. 2021): one-step model-predictive control
  in the contrastive latent space: of `num_samples` moves drawn uniformly in
  [-max_step, max_step]^6 (limited as the driver executes them),
  a* = argmin_a || T(phi(S), a) - phi(S_E[T-1]) ||, the move whose predicted
  latent is nearest the latent of the demo's final frame. The episode ends
  when ||phi(S) - phi(S_E[T-1])|| <= ||phi(S_E[T-2]) - phi(S_E[T-1])|| (no
  further from the final frame than the demo's own last step was).
- **TCN** (`TcnPlanner`, Sermanet et al. 2018): reward of a state s reached
  at episode step t, r_t(s) = -|| e(s) - e(S_E[tau(t)]) ||, e the unit-length
  time-contrastive embedding fine-tuned on the demo's frames, with the time
  alignment

      tau(t) = min(T - 1, floor(t * (T - 1) / H + 1/2)),

  T the demo's frames and H the control steps the demo took (its frame
  times over the control period; H = T - 1 for one frame per step). Policy
  search: cross-entropy method over `horizon`-step sequences rolled out
  through f_D (batched), starting from a zero-mean Gaussian N(0, sigma^2),
  maximising sum_i gamma^i r_{t+i+1}(s_{t+i+1}); the first move of the best
  sequence is executed. The episode ends once t >= H and the state is no
  further from the demo's last frame in the embedding than the demo's own
  last step was.

`TcnMpc` is not a baseline of the paper: the TCN reward inside this paper's
own planner (action prior, safe set, hidden-corner hypotheses): method
`tcn_mpc`, which measures a reward swap, not TCN.
"""

import dataclasses as dc
import math
from typing import NamedTuple

import numpy as np
import torch
from fabric_imitation.learning.limits import (
    DriverLimits,
    gripper_positions,
    limit_actions,
)
from fabric_imitation.learning.mpc import Mpc


def _states(demo_states) -> torch.Tensor:
    states = torch.as_tensor(np.asarray(demo_states), dtype=torch.float32)
    if states.ndim != 3 or len(states) < 2:
        raise ValueError(
            f"demo_states must be (T >= 2, M, 3), got {tuple(states.shape)}"
        )
    return states


# --- Zero ---------------------------------------------------------------------


@dc.dataclass
class ZeroConfig:
    # A subgoal is reached where the goal recognizer's probability exceeds this.
    reached_probability: float = 0.5
    # Steps on one subgoal before the follower moves on without the
    # recognizer (demo frames are one control step apart: generous).
    max_tries: int = 8

    def __post_init__(self):
        if not 0 < self.reached_probability < 1:
            raise ValueError(
                f"reached_probability must be in (0, 1), got {self.reached_probability}"
            )
        if self.max_tries < 1:
            raise ValueError(f"max_tries must be positive, got {self.max_tries}")


class ZeroStep(NamedTuple):
    action: torch.Tensor | None  # (6,), None when the demo is done
    subgoal: int  # the demo frame aimed at
    tries: int  # steps spent on it, this one included
    gave_up: bool  # done because the last subgoal ran out of tries


class ZeroFollower:
    """Zero at run time (see the module docstring). `baselines`: anything
    with `zero_action(S, G)` and `zero_reached(S, G)` (batched over G)."""

    def __init__(
        self,
        baselines,
        demo_states,
        *,
        limits: DriverLimits,
        config: ZeroConfig | None = None,
    ):
        self.b = baselines
        self.states = _states(demo_states)
        self.T = len(self.states)
        self.limits = limits
        self.config = config or ZeroConfig()

    def decide(self, S, progress: int, tries: int, pose=None) -> ZeroStep:
        """From state S (M, 3), the last step's subgoal and the tries spent
        on it; `pose`: [x, y, yaw_rad] of the states' frame in world."""
        cfg = self.config
        S = torch.as_tensor(S, dtype=torch.float32)
        j = max(1, progress)
        reached = self.b.zero_reached(S, self.states[j:]) > cfg.reached_probability
        gave_up = False
        while j < self.T:
            if bool(reached[j - max(1, progress)]):
                gave_up = False
            elif tries >= cfg.max_tries:
                gave_up = True
            else:
                break
            j, tries = j + 1, 0
        if j >= self.T:
            return ZeroStep(None, self.T - 1, 0, gave_up)
        a = self.b.zero_action(S, self.states[j])
        a = limit_actions(gripper_positions(S), a, self.limits, pose)
        return ZeroStep(a, j, tries + 1, False)


# --- CFM ----------------------------------------------------------------------


@dc.dataclass
class CfmConfig:
    # Moves sampled uniformly in the per-axis bound each step.
    num_samples: int = 500

    def __post_init__(self):
        if self.num_samples < 1:
            raise ValueError(f"num_samples must be positive, got {self.num_samples}")


class CfmPlanner:
    """CFM at run time (see the module docstring). `baselines`: anything
    with `cfm_latent(P, S)` and `cfm_predict(S, A)`."""

    def __init__(
        self,
        baselines,
        demo_states,
        *,
        limits: DriverLimits,
        config: CfmConfig | None = None,
    ):
        self.b = baselines
        self.states = _states(demo_states)
        self.T = len(self.states)
        self.limits = limits
        self.config = config or CfmConfig()
        z = self.b.cfm_latent(self.states[-2:], self.states[-2])
        self.end_distance = float((z[0] - z[1]).norm())

    def goal_distance(self, S) -> float:
        """||phi(S) - phi(S_E[T-1])|| in the canonical frame of S."""
        S = torch.as_tensor(S, dtype=torch.float32)
        z = self.b.cfm_latent(torch.stack([S, self.states[-1]]), S)
        return float((z[0] - z[1]).norm())

    def finished(self, S) -> bool:
        return self.goal_distance(S) <= self.end_distance

    def decide(self, S, pose=None, seed: int = 0) -> tuple[torch.Tensor, int]:
        """(move (6), the demo frame nearest S in latent space, for logs)."""
        S = torch.as_tensor(S, dtype=torch.float32)
        gen = torch.Generator().manual_seed(seed)
        b = self.limits.max_step
        A = (torch.rand(self.config.num_samples, 6, generator=gen) * 2 - 1) * b
        A = limit_actions(gripper_positions(S), A, self.limits, pose)
        z = self.b.cfm_latent(torch.cat([S[None], self.states]), S)
        d = (self.b.cfm_predict(S, A) - z[-1]).norm(dim=-1)
        nearest = int((z[1:] - z[0]).norm(dim=-1).argmin())
        return A[d.argmin()], nearest


# --- TCN ----------------------------------------------------------------------


@dc.dataclass
class TcnConfig:
    num_samples: int = 300  # sequences per cross-entropy iteration
    horizon: int = 3  # control steps rolled out through f_D
    iterations: int = 3  # cross-entropy iterations
    elites: int = 30  # best sequences the Gaussian is refitted to
    sigma: float = 0.015  # [m] std of the initial zero-mean Gaussian
    gamma: float = 0.9  # discount of later rollout steps

    def __post_init__(self):
        for name in ("num_samples", "horizon", "iterations", "elites"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if self.elites > self.num_samples:
            raise ValueError(
                f"elites must be at most num_samples, got {self.elites} > "
                f"{self.num_samples}"
            )
        if not self.sigma > 0 or not 0 < self.gamma <= 1:
            raise ValueError(
                f"sigma must be positive and gamma in (0, 1], got {self.sigma}, "
                f"{self.gamma}"
            )


def aligned_frame(t: int, T: int, H: int) -> int:
    """tau(t) = min(T - 1, floor(t (T - 1) / H + 1/2)): the demo frame (of T,
    the demo taking H control steps) that episode step t is compared with."""
    return min(T - 1, math.floor(t * (T - 1) / max(H, 1) + 0.5))


class TcnPlanner:
    """TCN at run time (see the module docstring). `baselines`: anything
    with `tcn_embed(P, S)` (the embedding fine-tuned on the demo);
    `dynamics`: anything with batched `forward(S, A)` (f_D); `demo_steps`:
    H, the control steps the demo took (None: T - 1)."""

    def __init__(
        self,
        baselines,
        dynamics,
        demo_states,
        *,
        limits: DriverLimits,
        demo_steps: int | None = None,
        config: TcnConfig | None = None,
    ):
        self.b = baselines
        self.dynamics = dynamics
        self.states = _states(demo_states)
        self.T = len(self.states)
        self.H = self.T - 1 if demo_steps is None else int(demo_steps)
        if self.H < 1:
            raise ValueError(f"demo_steps must be positive, got {demo_steps}")
        self.limits = limits
        self.config = config or TcnConfig()
        z = self.b.tcn_embed(self.states[-2:], self.states[-2])
        self.end_distance = float((z[0] - z[1]).norm())

    def aligned(self, t: int) -> int:
        return aligned_frame(t, self.T, self.H)

    def finished(self, S, steps: int) -> bool:
        if steps < self.H:
            return False
        S = torch.as_tensor(S, dtype=torch.float32)
        z = self.b.tcn_embed(torch.stack([S, self.states[-1]]), S)
        return float((z[0] - z[1]).norm()) <= self.end_distance

    @torch.no_grad()
    def rollout(self, S, X, step: int, pose=None):
        """(moves X (N, h, 6) as the driver executes them, discounted TCN
        rewards (N,)) of sequences from state S (M, 3) at episode step
        `step`, through f_D."""
        cfg = self.config
        goals = self.states[[self.aligned(step + i + 1) for i in range(cfg.horizon)]]
        z_goal = self.b.tcn_embed(goals, S)  # (h, latent)
        s = S.expand(len(X), *S.shape)
        executed, reward = [], torch.zeros(len(X))
        for i in range(cfg.horizon):
            a = limit_actions(gripper_positions(s), X[:, i], self.limits, pose)
            s = torch.as_tensor(self.dynamics.forward(s, a), dtype=torch.float32)
            z = self.b.tcn_embed(s, S)
            reward -= cfg.gamma**i * (z - z_goal[i]).norm(dim=-1)
            executed.append(a)
        return torch.stack(executed, 1), reward

    @torch.no_grad()
    def decide(self, S, step: int, pose=None, seed: int = 0):
        """(move (6), the aligned demo frame tau(step), iterations)."""
        cfg = self.config
        S = torch.as_tensor(S, dtype=torch.float32)
        gen = torch.Generator().manual_seed(seed)
        mu = torch.zeros(cfg.horizon, 6)
        std = torch.full((cfg.horizon, 6), cfg.sigma)
        best_r, best_a = -float("inf"), torch.zeros(6)
        for _ in range(cfg.iterations):
            X = mu + std * torch.randn(cfg.num_samples, cfg.horizon, 6, generator=gen)
            X[0] = mu
            executed, reward = self.rollout(S, X, step, pose)
            top = reward.topk(cfg.elites).indices
            if float(reward[top[0]]) > best_r:
                best_r, best_a = float(reward[top[0]]), executed[top[0], 0]
            mu = executed[top].mean(0)
            std = executed[top].std(0, unbiased=False).clamp_min(1e-4)
        return best_a, self.aligned(step), cfg.iterations


# --- the TCN reward on this paper's planner (method tcn_mpc) -------------------


class TcnMpc(Mpc):
    """This paper's sampling planner, action prior and safety rules with the
    TCN reward: minus the embedding distance of each predicted state to the
    time-aligned demo state (control step k + i + 1 for rollout step i, the
    last one after the demo's end). Progress is the time step; the episode
    ends once the demo's time is up and the state is no further from the
    last demo state in the embedding than the demo's own last step was, or
    at the step cap. Not the paper's TCN baseline (`TcnPlanner`): a reward
    swap inside the method."""

    def __init__(self, *, baselines, **kwargs):
        super().__init__(**kwargs)
        self.b = baselines
        self._step = 0
        states = self.demo.states
        z = self.b.tcn_embed(states[-2:], states[-1]) if self.demo.T > 1 else None
        self._end_distance = float((z[0] - z[1]).norm()) if z is not None else 0.0

    def finished(self, S, steps: int) -> bool:
        if steps < self.demo.T - 1:
            return False
        last = self.demo.states[-1]
        z = self.b.tcn_embed(torch.stack([S, last]), S)
        return float((z[0] - z[1]).norm()) <= self._end_distance

    def _aligned_index(self, i) -> int:
        """The demo step time-aligned with rollout step i."""
        return min(self._step + i + 1, self.demo.T - 1)

    def _aligned(self, i) -> torch.Tensor:
        return self.demo.states[self._aligned_index(i)]

    def current_progress(self, S, step):
        self._step = step
        return min(step, self.demo.T - 1)

    def _subgoal_index(self, s, window, i):
        return torch.full((len(s),), self._aligned_index(i), dtype=torch.long)

    @torch.no_grad()
    def rollout(self, S, X, window):
        cfg = self.config
        states = self._predicted_states(S, X)
        reward = torch.zeros(len(X))
        for i in range(cfg.horizon):
            goal = self._aligned(i)
            z = self.b.tcn_embed(torch.cat([states[i + 1], goal[None]]), S)
            reward -= cfg.gamma**i * (z[:-1] - z[-1]).norm(dim=-1)
        return reward, self._cost(states, X)
