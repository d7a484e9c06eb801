"""The paper's baselines (Table I), on the keypoint state the method uses:

- **Zero** (Pathak et al. 2018, zero-shot visual imitation): a goal-
  conditioned inverse model pi(s, g) trained with a forward-consistency loss
  (the predicted action, passed through a learned forward model F, must reach
  the goal), stepping through the demo's states as subgoals (`ZeroFollower`).
- **CFM** (Yan et al. 2021, contrastive forward model): an encoder phi and a
  latent forward model T trained with InfoNCE (the other transitions of the
  batch are the negatives); one-step model-predictive control: of sampled
  valid actions, the one whose predicted latent is nearest the next demo
  state's latent (`CfmPlanner`).
- **TCN** (Sermanet et al. 2018, time-contrastive networks): an embedding
  trained with a triplet loss (positives near in time, negatives far) on the
  exploration sequences, then on the demo; reward = minus the embedding
  distance to the time-aligned demo state, optimised by the method's own
  sampling planner and safety rules (`TcnMpc`).

Every network is an MLP with two hidden layers of 256 and ReLU (as the
paper's), trained on the prior dataset's keypoints by `train_baselines`
(`fabric-imitate train-baselines`). As f_D and f_I, each network sees states
in the canonical frame of the current state (learning/geometry.py), so the
frame the states come in (world in the prior scene, the object frame in a
task) does not matter; at run time the states are f_R's estimates.
"""

import dataclasses as dc
import time
from pathlib import Path

import numpy as np
import torch
from fabric_imitation.learning.checkpoint import (
    ReadTensorCheckpoint,
    WriteTensorCheckpoint,
)
from fabric_imitation.learning.errors import InputError
from fabric_imitation.learning.geometry import (
    canonical_frame,
    rotate_actions,
    to_frame,
)
from fabric_imitation.learning.models import Mlp
from fabric_imitation.learning.mpc import Mpc
from fabric_imitation.learning.priors import Normalizer
from fabric_imitation.learning.safety import valid_actions
from torch.nn import functional as F  # noqa: N812 (torch's own idiom)

BASELINES = ("zero", "cfm", "tcn")
FORMAT = "fabric-imitation-baselines"
VERSION = 1
BASELINES_JSON = "baselines.json"
BASELINES_FILE = "baselines.pt"
NETS = ("zero_inverse", "zero_forward", "cfm_encoder", "cfm_transition", "tcn")


@dc.dataclass
class BaselineTrainConfig:
    epochs: int = 20  # as f_D and f_I
    batch_size: int = 256  # also CFM's negatives per positive (batch - 1)
    lr: float = 1e-3
    latent: int = 32  # CFM's and TCN's embedding size
    # Zero: weight of the forward-consistency term.
    consistency_weight: float = 1.0
    # CFM: InfoNCE temperature on negative squared latent distances.
    temperature: float = 1.0
    # TCN: positives at most this many steps from the anchor, negatives at
    # least this many; triplet margin on unit-length embeddings.
    tcn_positive_steps: int = 1
    tcn_negative_steps: int = 4
    tcn_margin: float = 0.2
    # TCN on the demo (`Baselines.tcn_on_demo`): passes and learning rate.
    tcn_demo_steps: int = 200
    tcn_demo_lr: float = 3e-4
    holdout_fraction: float = 0.1  # of the episodes
    seed: int = 0


class Baselines:
    """The baselines' trained networks with their normalisers.

    States are (..., M, 3) in any frame with z up; actions (..., 6) are the
    two grippers' moves in that frame."""

    def __init__(self, *, num_keypoints: int, latent: int, norms: dict, config: dict):
        m3 = 3 * num_keypoints
        self.num_keypoints = num_keypoints
        self.latent = latent
        self.config = config
        self.nets = {
            "zero_inverse": Mlp(2 * m3, 6),
            "zero_forward": Mlp(m3 + 6, m3),
            "cfm_encoder": Mlp(m3, latent),
            "cfm_transition": Mlp(latent + 6, latent),
            "tcn": Mlp(m3, latent),
        }
        self.norms = norms  # state, action, delta (as the priors')
        self.metrics: dict = {}
        for net in self.nets.values():
            net.eval()

    # --- inputs in the current state's canonical frame ----------------------

    def _frame(self, S):
        return canonical_frame(torch.as_tensor(S, dtype=torch.float32))

    def _state(self, P, origin, yaw):
        """Normalised, flattened points P (..., M, 3) in the frame."""
        P = torch.as_tensor(P, dtype=torch.float32)
        return self.norms["state"].encode(to_frame(P, origin, yaw).flatten(-2))

    # --- Zero ----------------------------------------------------------------

    @torch.no_grad()
    def zero_action(self, S, G) -> torch.Tensor:
        """pi(S, G): the move (6) from state S towards goal state G."""
        origin, yaw = self._frame(S)
        x = torch.cat([self._state(S, origin, yaw), self._state(G, origin, yaw)], -1)
        a = self.norms["action"].decode(self.nets["zero_inverse"](x))
        return rotate_actions(a, yaw)

    # --- CFM -----------------------------------------------------------------

    @torch.no_grad()
    def cfm_latent(self, P, S) -> torch.Tensor:
        """phi of states P (..., M, 3), in the canonical frame of state S."""
        origin, yaw = self._frame(S)
        return self.nets["cfm_encoder"](self._state(P, origin, yaw))

    @torch.no_grad()
    def cfm_predict(self, S, A) -> torch.Tensor:
        """T(phi(S), A): predicted latents (N, latent) of actions A (N, 6)."""
        origin, yaw = self._frame(S)
        z = self.nets["cfm_encoder"](self._state(S, origin, yaw))
        a = self.norms["action"].encode(rotate_actions(A, -yaw))
        return self.nets["cfm_transition"](torch.cat([z.expand(len(a), -1), a], -1))

    # --- TCN -----------------------------------------------------------------

    @torch.no_grad()
    def tcn_embed(self, P, S) -> torch.Tensor:
        """Unit-length TCN embeddings of states P (..., M, 3), in the canonical
        frame of state S."""
        origin, yaw = self._frame(S)
        return F.normalize(self.nets["tcn"](self._state(P, origin, yaw)), dim=-1)

    def tcn_on_demo(self, demo_states: np.ndarray, cfg: BaselineTrainConfig):
        """A copy whose TCN is also trained on the demo's sequence (the
        time-contrastive network sees the demonstration, as in Sermanet et
        al.); the other networks are shared. Returns (copy, seconds)."""
        t0 = time.perf_counter()
        other = Baselines(
            num_keypoints=self.num_keypoints,
            latent=self.latent,
            norms=self.norms,
            config=self.config,
        )
        other.nets = dict(self.nets)
        other.metrics = self.metrics
        tcn = Mlp(3 * self.num_keypoints, self.latent)
        tcn.load_state_dict(self.nets["tcn"].state_dict())
        states = torch.as_tensor(np.asarray(demo_states), dtype=torch.float32)
        gen = torch.Generator().manual_seed(cfg.seed)
        opt = torch.optim.Adam(tcn.parameters(), lr=cfg.tcn_demo_lr)
        episode = torch.zeros(len(states), dtype=torch.long)
        triplets = _tcn_triplets(episode, torch.arange(len(states)), cfg)
        if triplets is not None:
            tcn.train()
            for _ in range(cfg.tcn_demo_steps):
                loss = _tcn_loss(tcn, self.norms, states, triplets, cfg, gen)
                opt.zero_grad()
                loss.backward()
                opt.step()
        other.nets["tcn"] = tcn.eval()
        return other, time.perf_counter() - t0

    # --- checkpoint ------------------------------------------------------------

    def save(self, directory: Path, *, extra: dict | None = None) -> Path:
        tensors = {
            f"{name}.{k}": v
            for name in NETS
            for k, v in self.nets[name].state_dict().items()
        }
        for name, norm in self.norms.items():
            tensors[f"norms.{name}.mean"] = norm.mean
            tensors[f"norms.{name}.std"] = norm.std
        return WriteTensorCheckpoint(
            directory,
            json_name=BASELINES_JSON,
            tensors_name=BASELINES_FILE,
            tensors=tensors,
            description={
                "format": FORMAT,
                "version": VERSION,
                "num_keypoints": self.num_keypoints,
                "latent": self.latent,
                "config": self.config,
                "norms": sorted(self.norms),
                "metrics": self.metrics,
                **(extra or {}),
            },
        )


def load_baselines(path: Path | str, *, num_keypoints: int | None = None) -> Baselines:
    """Loads the baselines' networks from a checkpoint directory.

    Raises:
        InputError: missing or corrupt file, another format or version, a
            checksum mismatch, a file that needs pickle, networks that do not
            fit, another number of keypoints.
    """
    description, tensors, file = ReadTensorCheckpoint(
        path,
        json_name=BASELINES_JSON,
        tensors_name=BASELINES_FILE,
        fmt=FORMAT,
        version=VERSION,
        what="baselines",
        retrain="retrain with `fabric-imitate train-baselines`",
    )
    m = int(description["num_keypoints"])
    if num_keypoints is not None and m != num_keypoints:
        raise InputError(
            f"baselines {file} use {m} keypoints, the scenario uses {num_keypoints}"
        )
    norms = {}
    for name in description["norms"]:
        mean, std = tensors.get(f"norms.{name}.mean"), tensors.get(f"norms.{name}.std")
        if mean is None or std is None:
            raise InputError(f"baselines {file} lack the {name} normaliser")
        norms[name] = Normalizer(mean, std)
    out = Baselines(
        num_keypoints=m,
        latent=int(description["latent"]),
        norms=norms,
        config=description["config"],
    )
    try:
        for name in NETS:
            out.nets[name].load_state_dict(
                {
                    k[len(name) + 1 :]: v
                    for k, v in tensors.items()
                    if k.startswith(name + ".")
                }
            )
    except RuntimeError as e:
        raise InputError(
            f"baselines {file} do not fit the networks: "
            f"{' '.join(str(e).split())[:150]}"
        ) from None
    out.metrics = description.get("metrics", {})
    return out


# --- training -------------------------------------------------------------------


def _canonical_triples(S, Sn, A):
    origin, yaw = canonical_frame(S)
    return (
        to_frame(S, origin, yaw).flatten(-2),
        to_frame(Sn, origin, yaw).flatten(-2),
        rotate_actions(A, -yaw),
    )


def _tcn_triplets(episode: torch.Tensor, step: torch.Tensor, cfg):
    """All (anchor, positive) index pairs of a sequence set, with the mask of
    allowed negatives found per batch (same episode, far in time)."""
    pairs = []
    n = len(episode)
    for d in range(1, cfg.tcn_positive_steps + 1):
        i = torch.arange(n - d)
        ok = episode[i] == episode[i + d]
        pairs += [
            torch.stack([i[ok], i[ok] + d], 1),
            torch.stack([i[ok] + d, i[ok]], 1),
        ]
    if not pairs:
        return None
    pairs = torch.cat(pairs)
    return {"pairs": pairs, "episode": episode, "step": step} if len(pairs) else None


def _tcn_loss(net, norms, states, triplets, cfg, gen, batch: int = 256):
    """Triplet loss on a random batch of (anchor, positive) pairs, each with a
    negative drawn from the same sequence at least tcn_negative_steps away;
    all three in the anchor's canonical frame."""
    pairs, episode, step = triplets["pairs"], triplets["episode"], triplets["step"]
    pick = torch.randint(len(pairs), (min(batch, len(pairs)),), generator=gen)
    a, p = pairs[pick, 0], pairs[pick, 1]
    # Negatives: rejection-sample indices of the same episode, far in time.
    neg = torch.randint(len(episode), (len(a), 16), generator=gen)
    ok = (episode[neg] == episode[a, None]) & (
        (step[neg] - step[a, None]).abs() >= cfg.tcn_negative_steps
    )
    has = ok.any(1)
    if not has.any():  # nothing far enough: sample along the sequence instead
        return torch.zeros((), requires_grad=True)
    a, p = a[has], p[has]
    n = neg[has].gather(1, ok[has].float().argmax(1, keepdim=True))[:, 0]
    origin, yaw = canonical_frame(states[a])

    def embed(idx):
        x = norms["state"].encode(to_frame(states[idx], origin, yaw).flatten(-2))
        return F.normalize(net(x), dim=-1)

    za, zp, zn = embed(a), embed(p), embed(n)
    d_pos = (za - zp).pow(2).sum(-1)
    d_neg = (za - zn).pow(2).sum(-1)
    return F.relu(d_pos - d_neg + cfg.tcn_margin).mean()


def train_baselines(ds, *, cfg: BaselineTrainConfig | None = None, log=print):
    """Trains Zero's, CFM's and TCN's networks on the prior dataset `ds`
    (learning/dataset.py; keypoints only). Returns Baselines with held-out
    metrics in `.metrics`."""
    from fabric_imitation.learning.train import _split

    cfg = cfg or BaselineTrainConfig()
    torch.manual_seed(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    t0 = time.perf_counter()
    S = torch.as_tensor(ds.arrays["keypoints"], dtype=torch.float32)
    Sn = torch.as_tensor(ds.arrays["keypoints_next"], dtype=torch.float32)
    A = torch.as_tensor(ds.arrays["action"], dtype=torch.float32)
    episode = torch.as_tensor(ds.arrays["episode"].astype(np.int64))
    step = torch.as_tensor(ds.arrays["step"].astype(np.int64))
    tr, va = (torch.as_tensor(i) for i in _split(ds, cfg.holdout_fraction, cfg.seed))
    x, xn, a = _canonical_triples(S, Sn, A)
    norms = {
        "state": Normalizer.fit(torch.cat([x[tr], xn[tr]])),
        "action": Normalizer.fit(a[tr]),
        "delta": Normalizer.fit((xn - x)[tr]),
    }
    m = S.shape[-2]
    out = Baselines(
        num_keypoints=m, latent=cfg.latent, norms=norms, config=dc.asdict(cfg)
    )
    xs, xns = norms["state"].encode(x), norms["state"].encode(xn)
    an, dn = norms["action"].encode(a), norms["delta"].encode(xn - x)
    nets = out.nets
    params = [p for name in NETS if name != "tcn" for p in nets[name].parameters()]
    opt = torch.optim.Adam(params, lr=cfg.lr)
    tcn_opt = torch.optim.Adam(nets["tcn"].parameters(), lr=cfg.lr)
    # The sequences of the training episodes, in dataset order: the states
    # of each step (the last step's next state is left out).
    train_mask = torch.zeros(len(S), dtype=torch.bool)
    train_mask[tr] = True
    triplets = _tcn_triplets(episode[train_mask], step[train_mask], cfg)
    tcn_states = S[train_mask]

    def losses(idx):
        zi = nets["zero_inverse"](torch.cat([xs[idx], xns[idx]], -1))
        forward = nets["zero_forward"]
        l_inv = F.mse_loss(zi, an[idx])
        l_fwd = F.mse_loss(forward(torch.cat([xs[idx], an[idx]], -1)), dn[idx])
        l_con = F.mse_loss(forward(torch.cat([xs[idx], zi], -1)), dn[idx])
        z = nets["cfm_encoder"](xs[idx])
        z_next = nets["cfm_encoder"](xns[idx])
        z_pred = nets["cfm_transition"](torch.cat([z, an[idx]], -1))
        logits = -torch.cdist(z_pred, z_next).pow(2) / cfg.temperature
        l_nce = F.cross_entropy(logits, torch.arange(len(idx)))
        return l_inv, l_fwd, l_con, l_nce

    curves = []
    for epoch in range(cfg.epochs):
        for net in nets.values():
            net.train()
        perm = tr[torch.randperm(len(tr), generator=gen)]
        total = np.zeros(5)
        batches = 0
        for i in range(0, len(perm) - cfg.batch_size + 1, cfg.batch_size):
            idx = perm[i : i + cfg.batch_size]
            l_inv, l_fwd, l_con, l_nce = losses(idx)
            loss = l_inv + l_fwd + cfg.consistency_weight * l_con + l_nce
            opt.zero_grad()
            loss.backward()
            opt.step()
            l_tcn = _tcn_loss(nets["tcn"], norms, tcn_states, triplets, cfg, gen)
            tcn_opt.zero_grad()
            l_tcn.backward()
            tcn_opt.step()
            total += [float(v.detach()) for v in (l_inv, l_fwd, l_con, l_nce, l_tcn)]
            batches += 1
        for net in nets.values():
            net.eval()
        curves.append((total / max(batches, 1)).round(4).tolist())
        log(
            f"baselines epoch {epoch + 1}/{cfg.epochs}: inverse {curves[-1][0]:.4f} "
            f"forward {curves[-1][1]:.4f} consistency {curves[-1][2]:.4f} "
            f"infonce {curves[-1][3]:.3f} triplet {curves[-1][4]:.4f}"
        )
    out.metrics = {
        **_heldout_metrics(out, S[va], Sn[va], A[va], episode[va], step[va], cfg),
        "train_transitions": len(tr),
        "heldout_transitions": len(va),
        "train_seconds": round(time.perf_counter() - t0, 1),
        "curves": {
            "columns": ["inverse", "forward", "consistency", "infonce", "triplet"],
            "per_epoch": curves,
        },
    }
    return out


@torch.no_grad()
def _heldout_metrics(b: Baselines, S, Sn, A, episode, step, cfg) -> dict:
    """Zero: the inverse model's action error against the no-move action;
    CFM: top-1 accuracy of the true next state among up to 256 held-out
    ones (by predicted latent); TCN: how often the embedding puts the next step
    nearer than a step tcn_negative_steps or more away (same episode)."""
    if len(S) == 0:
        return {}
    a_hat = torch.stack([b.zero_action(s, sn) for s, sn in zip(S, Sn, strict=True)])
    out = {
        "zero_action_error_mm": round(1000 * float((a_hat - A).norm(dim=-1).mean()), 2),
        "mean_action_mm": round(1000 * float(A.norm(dim=-1).mean()), 2),
    }
    n = min(256, len(S))
    hits = 0
    for i in range(n):
        z_pred = b.cfm_predict(S[i], A[i : i + 1])
        z_all = b.cfm_latent(Sn[:n], S[i])
        hits += int((z_all - z_pred).norm(dim=-1).argmin() == i)
    out["cfm_top1"] = round(hits / n, 3)
    out["cfm_candidates"] = n
    right = total = 0
    for i in range(len(S) - 1):
        if episode[i + 1] != episode[i]:
            continue
        far = torch.nonzero(
            (episode == episode[i]) & ((step - step[i]).abs() >= cfg.tcn_negative_steps)
        )[:, 0]
        if len(far) == 0:
            continue
        z = b.tcn_embed(torch.stack([S[i], S[i + 1], S[far[0]]]), S[i])
        right += int((z[0] - z[1]).norm() < (z[0] - z[2]).norm())
        total += 1
    out["tcn_near_before_far"] = round(right / max(total, 1), 3)
    return out


# --- acting ---------------------------------------------------------------------


class ZeroFollower:
    """Zero at run time: subgoal j starts at demo state 1; each step the
    goal-conditioned inverse model moves towards it, and j advances when the
    state is within `reach` (mean keypoint distance [m]) of it or after
    `patience` steps on it; the episode ends after the last demo state."""

    def __init__(
        self,
        baselines: Baselines,
        demo_states,
        *,
        max_step: float,
        reach: float = 0.02,
        patience: int = 3,
    ):
        self.b = baselines
        self.states = torch.as_tensor(np.asarray(demo_states), dtype=torch.float32)
        self.T = len(self.states)
        self.max_step, self.reach, self.patience = max_step, reach, patience

    def decide(self, S, progress: int, tries: int):
        """(action (6) or None when done, subgoal, tries on it)."""
        j = max(1, progress)
        while j < self.T and (
            (S - self.states[j]).norm(dim=-1).mean() < self.reach
            or tries >= self.patience
        ):
            j, tries = j + 1, 0
        if j >= self.T:
            return None, self.T - 1, 0
        a = self.b.zero_action(S, self.states[j]).clamp(-self.max_step, self.max_step)
        return a, j, tries + 1


class CfmPlanner:
    """CFM at run time: progress J is the demo state nearest in latent space
    (searched from J - 1 to J + 2); of `num_samples` valid actions (uniform
    in the step bounds, the safety rules with the grasped corners moved),
    the one whose predicted latent is nearest the latent of demo state J + 1;
    the episode ends when J reaches the last demo state."""

    def __init__(
        self,
        baselines: Baselines,
        demo_states,
        *,
        safety,
        safety_ctx,
        num_samples: int = 500,
    ):
        self.b = baselines
        self.states = torch.as_tensor(np.asarray(demo_states), dtype=torch.float32)
        self.T = len(self.states)
        self.safety, self.ctx = safety, safety_ctx
        self.num_samples = num_samples

    def progress(self, S, previous: int) -> int:
        lo, hi = max(0, previous - 1), min(self.T, previous + 3)
        z = self.b.cfm_latent(torch.cat([S[None], self.states[lo:hi]]), S)
        return lo + int((z[1:] - z[0]).norm(dim=-1).argmin())

    def decide(self, S, previous: int, pose, seed: int):
        """(action (6) or None when done or no valid action, J, valid count)."""
        J = self.progress(S, previous)
        if J >= self.T - 1:
            return None, J, 0
        gen = torch.Generator().manual_seed(seed)
        b = self.safety.max_step
        A = (torch.rand(self.num_samples, 6, generator=gen) * 2 - 1) * b
        ctx = dc.replace(self.ctx, frame_pose=np.asarray(pose, float))
        ok = valid_actions(S.expand(len(A), *S.shape), A, self.safety, ctx)
        if not ok.any():
            return None, J, 0
        A = A[ok]
        target = self.b.cfm_latent(self.states[J + 1], S)
        d = (self.b.cfm_predict(S, A) - target).norm(dim=-1)
        return A[d.argmin()], J, int(ok.sum())


class TcnMpc(Mpc):
    """The method's sampling planner, action prior and safety rules with the
    TCN reward: minus the embedding distance of each predicted state to the
    time-aligned demo state (control step k + i + 1 for rollout step i, the
    last one after the demo's end). Progress is the time step; the episode
    ends once the demo's time is up and the state is no further from the
    last demo state in the embedding than the demo's own last step was, or
    at the step cap."""

    def __init__(self, *, baselines: Baselines, **kwargs):
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

    def _aligned(self, i) -> torch.Tensor:
        return self.demo.states[min(self._step + i + 1, self.demo.T - 1)]

    def current_progress(self, S, step, previous_progress):
        self._step = step
        return min(step, self.demo.T - 1)

    def subgoal(self, s, window, i):
        return self._aligned(i)[None].expand(len(s), -1, -1)

    @torch.no_grad()
    def rollout(self, S, X, window):
        cfg = self.config
        cost = torch.zeros(len(X))
        reward = torch.zeros(len(X))
        for i, (s, a, s_next) in enumerate(self._predicted_steps(S, X)):
            ok = valid_actions(s, a, self.safety, self.ctx, S_next=s_next)
            cost += (~ok).float()
            goal = self._aligned(i)
            z = self.b.tcn_embed(torch.cat([s_next, goal[None]]), S)
            reward -= cfg.gamma**i * (z[:-1] - z[-1]).norm(dim=-1)
        return reward, cost


def BaselinesSummary(b: Baselines) -> dict:
    return {k: v for k, v in b.metrics.items() if k != "curves"}


def TrainBaselines(
    *, data: Path, out: Path, config: BaselineTrainConfig | None = None, log=None
) -> dict:
    """`fabric-imitate train-baselines`: trains Zero's, CFM's and TCN's
    networks on the prior dataset `data` and writes them to `out`
    (baselines.json + baselines.pt, next to the priors). Returns a summary."""
    import sys

    from fabric_imitation.learning.dataset import LoadDataset

    cfg = config or BaselineTrainConfig()
    ds = LoadDataset(data, images=False)

    def _log(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    baselines = train_baselines(ds, cfg=cfg, log=log or _log)
    path = baselines.save(
        Path(out),
        extra={
            "dataset": {
                "file": Path(data).name,
                "fingerprint": ds.fingerprint,
                "transitions": len(ds),
            }
        },
    )
    return {
        "checkpoint": str(path),
        "dataset_fingerprint": ds.fingerprint,
        **BaselinesSummary(baselines),
    }
