"""The paper's baselines' networks (Table I), on the keypoint state the
method uses, trained on the shared prior dataset; their run-time decisions
are in learning/baseline_policies.py.

- **Zero** (Pathak et al. 2018, zero-shot visual imitation): a goal-
  conditioned inverse model pi(s, g) trained with a forward-consistency loss
  (the predicted action, passed through a learned forward model F, must reach
  the goal), and a goal recognizer r(s, g) in [0, 1]: has state s reached
  goal g? Its positives are pairs of states of the same prior episode at most
  `recognizer_positive_steps` control steps apart, its negatives pairs at
  least `recognizer_negative_steps` apart (binary cross-entropy, half of each
  per batch).
- **CFM** (Yan et al. 2021, contrastive forward model): an encoder phi and a
  latent forward model T trained with InfoNCE (the other transitions of the
  batch are the negatives).
- **TCN** (Sermanet et al. 2018, time-contrastive networks): an embedding
  trained with a triplet loss (positives near in time, negatives far) on the
  exploration sequences, then fine-tuned on the demo's sequence
  (`Baselines.tcn_on_demo`).

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
from fabric_imitation.learning.priors import Normalizer
from torch.nn import functional as F  # noqa: N812 (torch's own idiom)

BASELINES = ("zero", "cfm", "tcn")
FORMAT = "fabric-imitation-baselines"
VERSION = 1
BASELINES_JSON = "baselines.json"
BASELINES_FILE = "baselines.pt"
NETS = (
    "zero_inverse",
    "zero_forward",
    "zero_recognizer",
    "cfm_encoder",
    "cfm_transition",
    "tcn",
)


@dc.dataclass
class BaselineTrainConfig:
    epochs: int = 20  # as f_D and f_I
    batch_size: int = 256  # also CFM's negatives per positive (batch - 1)
    lr: float = 1e-3
    latent: int = 32  # CFM's and TCN's embedding size
    # Zero: weight of the forward-consistency term.
    consistency_weight: float = 1.0
    # Zero's goal recognizer: a goal at most this many steps from the state
    # (same episode) is reached, one at least this many is not.
    recognizer_positive_steps: int = 1
    recognizer_negative_steps: int = 3
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

    def __post_init__(self):
        for name in ("epochs", "batch_size", "latent", "tcn_positive_steps"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if not 0 <= self.recognizer_positive_steps < self.recognizer_negative_steps:
            raise ValueError(
                "recognizer_positive_steps must be in [0, recognizer_negative_"
                f"steps), got {self.recognizer_positive_steps} and "
                f"{self.recognizer_negative_steps}"
            )
        if not self.tcn_positive_steps < self.tcn_negative_steps:
            raise ValueError(
                "tcn_negative_steps must exceed tcn_positive_steps, got "
                f"{self.tcn_negative_steps}"
            )


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
            "zero_recognizer": Mlp(2 * m3, 1),
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

    @torch.no_grad()
    def zero_reached(self, S, G) -> torch.Tensor:
        """r(S, G): the goal recognizer's probability (...) that state S
        (M, 3) has reached each goal state G (..., M, 3)."""
        origin, yaw = self._frame(S)
        g = self._state(G, origin, yaw)
        s = self._state(S, origin, yaw).expand(g.shape)
        logit = self.nets["zero_recognizer"](torch.cat([s, g], -1))
        return torch.sigmoid(logit[..., 0])

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
    for name in NETS:
        if not any(k.startswith(name + ".") for k in tensors):
            raise InputError(
                f"baselines {file} lack the {name} network; retrain with "
                "`fabric-imitate train-baselines`"
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


def _episode_bounds(episode: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """First and last row (each row's) of the runs of equal `episode`."""
    n = len(episode)
    rows = torch.arange(n)
    new = torch.ones(n, dtype=torch.bool)
    new[1:] = episode[1:] != episode[:-1]
    first = torch.cummax(torch.where(new, rows, 0), 0).values
    last_of = torch.ones(n, dtype=torch.bool)
    last_of[:-1] = new[1:]
    flipped = torch.where(last_of, rows, n).flip(0)
    last = torch.cummin(flipped, 0).values.flip(0)
    return first, last


def _recognizer_pairs(episode, step, n: int, cfg, gen):
    """(state rows, goal rows, labels) of about n pairs of a sequence set
    (each episode's rows together, in step order): half positives, the goal
    at most recognizer_positive_steps from the state, half negatives, at
    least recognizer_negative_steps (drawn uniformly over the episode; a
    state without one is left out)."""
    first, last = _episode_bounds(episode)
    P, N = cfg.recognizer_positive_steps, cfg.recognizer_negative_steps
    half = n // 2
    i = torch.randint(len(episode), (half,), generator=gen)
    j = (i + torch.randint(-P, P + 1, (half,), generator=gen)).clamp(first[i], last[i])
    j = torch.where((step[j] - step[i]).abs() <= P, j, i)
    k = torch.randint(len(episode), (n - half,), generator=gen)
    span = last[k] - first[k] + 1
    cand = first[k, None] + (
        torch.rand(len(k), 8, generator=gen) * span[:, None]
    ).long().clamp(max=span[:, None] - 1)
    far = (step[cand] - step[k, None]).abs() >= N
    has = far.any(1)
    neg = cand[has].gather(1, far[has].float().argmax(1, keepdim=True))[:, 0]
    states = torch.cat([i, k[has]])
    goals = torch.cat([j, neg])
    labels = torch.cat([torch.ones(len(i)), torch.zeros(len(neg))])
    return states, goals, labels


def _recognizer_logits(net, norms, states, goals):
    """Recognizer logits (B,) of states (B, M, 3) and goals (B, M, 3), both
    in the canonical frame of the state."""
    origin, yaw = canonical_frame(states)
    x = torch.cat(
        [
            norms["state"].encode(to_frame(P, origin, yaw).flatten(-2))
            for P in (states, goals)
        ],
        -1,
    )
    return net(x)[..., 0]


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
    seq_episode, seq_step = episode[train_mask], step[train_mask]

    def recognizer_loss():
        i, j, label = _recognizer_pairs(seq_episode, seq_step, cfg.batch_size, cfg, gen)
        logits = _recognizer_logits(
            nets["zero_recognizer"], norms, tcn_states[i], tcn_states[j]
        )
        return F.binary_cross_entropy_with_logits(logits, label)

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
        total = np.zeros(6)
        batches = 0
        for i in range(0, len(perm) - cfg.batch_size + 1, cfg.batch_size):
            l_inv, l_fwd, l_con, l_nce = losses(perm[i : i + cfg.batch_size])
            l_rec = recognizer_loss()
            _descend(
                opt, l_inv + l_fwd + cfg.consistency_weight * l_con + l_nce + l_rec
            )
            l_tcn = _tcn_loss(nets["tcn"], norms, tcn_states, triplets, cfg, gen)
            _descend(tcn_opt, l_tcn)
            total += [
                float(v.detach()) for v in (l_inv, l_fwd, l_con, l_nce, l_tcn, l_rec)
            ]
            batches += 1
        for net in nets.values():
            net.eval()
        curves.append((total / max(batches, 1)).round(4).tolist())
        log(
            f"baselines epoch {epoch + 1}/{cfg.epochs}: inverse {curves[-1][0]:.4f} "
            f"forward {curves[-1][1]:.4f} consistency {curves[-1][2]:.4f} "
            f"infonce {curves[-1][3]:.3f} triplet {curves[-1][4]:.4f} "
            f"recognizer {curves[-1][5]:.4f}"
        )
    out.metrics = {
        **_heldout_metrics(out, S[va], Sn[va], A[va], episode[va], step[va], cfg),
        "train_transitions": len(tr),
        "heldout_transitions": len(va),
        "train_seconds": round(time.perf_counter() - t0, 1),
        "curves": {
            "columns": [
                "inverse",
                "forward",
                "consistency",
                "infonce",
                "triplet",
                "recognizer",
            ],
            "per_epoch": curves,
        },
    }
    return out


def _descend(optimizer, loss) -> None:
    """One gradient step of `optimizer` on `loss`."""
    optimizer.zero_grad()
    loss.backward()
    optimizer.step()


@torch.no_grad()
def _heldout_metrics(b: Baselines, S, Sn, A, episode, step, cfg) -> dict:
    """Zero: the inverse model's action error against the no-move action,
    and the goal recognizer's accuracy on 2,000 held-out pairs (half
    positives) against the best single threshold on the mean keypoint
    distance (chosen on the same pairs, so optimistic for it); CFM: top-1
    accuracy of the true next state among up to 256 held-out ones (by
    predicted latent); TCN: how often the embedding puts the next step nearer
    than a step tcn_negative_steps or more away (same episode)."""
    if len(S) == 0:
        return {}
    a_hat = torch.stack([b.zero_action(s, sn) for s, sn in zip(S, Sn, strict=True)])
    out = {
        "zero_action_error_mm": round(1000 * float((a_hat - A).norm(dim=-1).mean()), 2),
        "mean_action_mm": round(1000 * float(A.norm(dim=-1).mean()), 2),
    }
    i, j, label = _recognizer_pairs(
        episode, step, 2000, cfg, torch.Generator().manual_seed(cfg.seed + 1)
    )
    if len(label):
        p = torch.sigmoid(
            _recognizer_logits(b.nets["zero_recognizer"], b.norms, S[i], S[j])
        )
        out["zero_recognizer_accuracy"] = round(
            float(((p > 0.5).float() == label).float().mean()), 3
        )
        out["zero_recognizer_pairs"] = len(label)
        out["zero_distance_rule_accuracy"] = _best_threshold_accuracy(
            (S[i] - S[j]).norm(dim=-1).mean(-1), label
        )
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


def _best_threshold_accuracy(distance: torch.Tensor, label: torch.Tensor) -> float:
    """Accuracy of the best rule "reached if distance <= threshold"."""
    order = distance.argsort()
    y = label[order]
    # Threshold after the k nearest: those k say reached, the rest not.
    right = torch.cat([torch.zeros(1), y.cumsum(0)]) + torch.cat(
        [(1 - y).flip(0).cumsum(0).flip(0), torch.zeros(1)]
    )
    return round(float(right.max()) / len(y), 3)


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
