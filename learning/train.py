"""`fabric-imitate train`: f_R, f_D, f_I from a prior dataset, with held-out
metrics, training curves (PNG) and a checkpoint (paper Sec. IV-B)."""

import copy
import dataclasses as dc
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
from fabric_imitation.learning.dataset import DecodeDepth, LoadDataset, PriorDataset
from fabric_imitation.learning.demo_io import CameraModel
from fabric_imitation.learning.errors import InputError
from fabric_imitation.learning.geometry import PinholeCamera, rotate_actions, to_frame
from fabric_imitation.learning.models import KeypointNetConfig
from fabric_imitation.learning.priors import (
    Normalizer,
    Priors,
    build_priors,
    canonical_inputs,
    image_input,
)
from torch.nn import functional as F  # noqa: N812 (torch's own idiom)

# Prior-dataset states kept in the checkpoint: the registration net f_A is
# trained on them when a demo arrives (the dataset itself is not shipped).
PRIOR_STATES_KEPT = 2000


@dc.dataclass
class TrainConfig:
    epochs: int = 20  # f_D, f_I (the paper's 20)
    # f_R: 10 passes reach the quality bar (0.9 px held out on 10,000
    # transitions) in 7.4 minutes on this 2-core machine.
    keypoint_epochs: int = 10
    batch_size: int = 128
    keypoint_batch_size: int = 32
    lr: float = 1e-3
    keypoint_lr: float = 2e-3
    holdout_fraction: float = 0.1  # of the episodes
    seed: int = 0
    # Augmentation of f_R's images: rotation about the principal point (exact
    # for a camera looking straight down) and shifts, so that a cloth turned
    # or moved on the table, as in a task scene, is in the training data.
    rotate_deg: float = 60.0
    shift_px: float = 16.0
    keypoint_net: KeypointNetConfig = dc.field(default_factory=KeypointNetConfig)


def _split(ds: PriorDataset, fraction: float, seed: int):
    episodes = np.unique(ds.arrays["episode"])
    rng = np.random.default_rng(seed)
    n_val = max(1, int(round(fraction * len(episodes)))) if len(episodes) > 1 else 0
    val_eps = (
        set(rng.choice(episodes, n_val, replace=False).tolist()) if n_val else set()
    )
    is_val = np.isin(ds.arrays["episode"], list(val_eps))
    if not is_val.any():  # one episode: hold out its last tenth of steps
        n = len(is_val)
        is_val[n - max(1, n // 10) :] = True
    return np.flatnonzero(~is_val), np.flatnonzero(is_val)


def _dynamics_tensors(ds: PriorDataset, idx: np.ndarray):
    S = torch.as_tensor(ds.arrays["keypoints"][idx])
    Sn = torch.as_tensor(ds.arrays["keypoints_next"][idx])
    A = torch.as_tensor(ds.arrays["action"][idx])
    Sc, origin, yaw = canonical_inputs(S)
    Snc = to_frame(Sn, origin, yaw)
    Ac = rotate_actions(A, -yaw)
    return Sc.flatten(-2), Snc.flatten(-2), Ac


def _fit_mlp(model, x_tr, y_tr, x_va, y_va, cfg: TrainConfig, name: str, log):
    gen = torch.Generator().manual_seed(cfg.seed)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    curve = []
    for epoch in range(cfg.epochs):
        model.train()
        perm = torch.randperm(len(x_tr), generator=gen)
        total = 0.0
        for i in range(0, len(perm), cfg.batch_size):
            b = perm[i : i + cfg.batch_size]
            loss = F.mse_loss(model(x_tr[b]), y_tr[b])
            opt.zero_grad()
            loss.backward()
            opt.step()
            total += loss.item() * len(b)
        model.eval()
        with torch.no_grad():
            val = F.mse_loss(model(x_va), y_va).item() if len(x_va) else float("nan")
        curve.append((total / len(x_tr), val))
        log(
            f"{name} epoch {epoch + 1}/{cfg.epochs} train {curve[-1][0]:.4f} "
            f"val {val:.4f}"
        )
    return curve


def _augment(
    x: torch.Tensor, uv: torch.Tensor, cfg: TrainConfig, center, gen: torch.Generator
):
    """Rotates/shifts images (B, C, H, W) and their keypoint pixels (B, M, 2)."""
    B, _, H, W = x.shape
    theta = (torch.rand(B, generator=gen) * 2 - 1) * math.radians(cfg.rotate_deg)
    shift = (torch.rand(B, 2, generator=gen) * 2 - 1) * cfg.shift_px
    c, s = torch.cos(theta), torch.sin(theta)
    R = torch.stack([torch.stack([c, -s], -1), torch.stack([s, c], -1)], -2)
    ctr = torch.as_tensor(center, dtype=torch.float32)
    # Output pixel q shows input pixel p = R^T (q - ctr - shift) + ctr.
    uv_new = (uv - ctr) @ R.transpose(-1, -2) + ctr + shift[:, None, :]
    # affine_grid maps output to input in normalised coordinates
    # n = D u + e (align_corners=False), so p = R^T (q - ctr - shift) + ctr
    # becomes n_p = D R^T D^-1 n_q + D R^T (-D^-1 e - ctr - shift) + D ctr + e.
    D = torch.diag(torch.tensor([2.0 / W, 2.0 / H]))
    Dinv = torch.diag(torch.tensor([W / 2.0, H / 2.0]))
    e = torch.tensor([1.0 / W - 1.0, 1.0 / H - 1.0])
    Rt = R.transpose(-1, -2)
    inner = -(Dinv @ e) - ctr - shift
    A = torch.zeros(B, 2, 3)
    A[:, :, :2] = D @ Rt @ Dinv
    A[:, :, 2] = (D @ Rt @ inner[..., None])[..., 0] + D @ ctr + e
    grid = F.affine_grid(A, list(x.shape), align_corners=False)
    out = F.grid_sample(
        x, grid, mode="nearest", padding_mode="zeros", align_corners=False
    )
    return out, uv_new


def _keypoint_labels(camera: PinholeCamera, ds: PriorDataset, idx: np.ndarray):
    return camera.project(torch.as_tensor(ds.arrays["keypoints"][idx]))


def _images(camera: PinholeCamera, ds: PriorDataset, idx: np.ndarray) -> torch.Tensor:
    mask = torch.as_tensor(ds.arrays["mask"][idx])
    depth = torch.as_tensor(DecodeDepth(ds.arrays["depth"][idx]))
    return image_input(camera, mask, depth)


def _fit_keypoints(priors: Priors, ds, tr, va, cfg: TrainConfig, log):
    camera = priors.camera
    net = priors.f_R
    gen = torch.Generator().manual_seed(cfg.seed + 1)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.keypoint_lr)
    steps = cfg.keypoint_epochs * math.ceil(len(tr) / cfg.keypoint_batch_size)
    sched = torch.optim.lr_scheduler.OneCycleLR(
        opt, max_lr=cfg.keypoint_lr, total_steps=max(steps, 1)
    )
    center = (float(camera.K[0, 2]), float(camera.K[1, 2]))
    x_va = _images(camera, ds, va)
    uv_va = _keypoint_labels(camera, ds, va)
    curve = []
    for epoch in range(cfg.keypoint_epochs):
        net.train()
        perm = torch.as_tensor(tr)[torch.randperm(len(tr), generator=gen)]
        total = 0.0
        for i in range(0, len(perm), cfg.keypoint_batch_size):
            b = perm[i : i + cfg.keypoint_batch_size].numpy()
            b.sort()
            x, uv = _augment(
                _images(camera, ds, b),
                _keypoint_labels(camera, ds, b),
                cfg,
                center,
                gen,
            )
            loss = F.smooth_l1_loss(net(x), uv, beta=2.0)
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            total += loss.item() * len(b)
        net.eval()
        with torch.no_grad():
            err = (net(x_va) - uv_va).norm(dim=-1).mean().item() if len(va) else 0.0
        curve.append((total / len(tr), err))
        log(
            f"f_R epoch {epoch + 1}/{cfg.keypoint_epochs} train {curve[-1][0]:.3f} "
            f"val pixel error {err:.2f}"
        )
    return curve


# Distance [m] between a keypoint and the surface seen at its pixel beyond
# which the keypoint counts as hidden from the camera.
HIDDEN_DISTANCE = 0.01


@torch.no_grad()
def evaluate(priors: Priors, ds: PriorDataset, idx: np.ndarray) -> dict:
    """Held-out metrics of the quality bar."""
    S = torch.as_tensor(ds.arrays["keypoints"][idx])
    Sn = torch.as_tensor(ds.arrays["keypoints_next"][idx])
    A = torch.as_tensor(ds.arrays["action"][idx])
    pred = priors.forward(S, A)
    fd = (pred - Sn).norm(dim=-1).mean().item()
    still = (S - Sn).norm(dim=-1).mean().item()
    fi = (priors.inverse(S, Sn) - A).reshape(-1, 2, 3).norm(dim=-1).mean().item()
    size = A.reshape(-1, 2, 3).norm(dim=-1).mean().item()
    out = {
        "heldout_transitions": int(len(idx)),
        "f_D_error_mm": round(1000 * fd, 2),
        "no_motion_baseline_mm": round(1000 * still, 2),
        "f_D_ratio": round(fd / max(still, 1e-9), 3),
        "f_I_error_mm": round(1000 * fi, 2),
        "mean_action_mm": round(1000 * size, 2),
        "f_I_ratio": round(fi / max(size, 1e-9), 3),
    }
    if "mask" in ds.arrays:
        mask = torch.as_tensor(ds.arrays["mask"][idx])
        depth = torch.as_tensor(DecodeDepth(ds.arrays["depth"][idx]))
        uv = priors.f_R(image_input(priors.camera, mask, depth))
        uv_true = priors.camera.project(S)
        p = priors.camera.back_project(uv, depth, mask)
        error = (p - S).norm(dim=-1)
        # A keypoint is hidden when the surface the camera sees at its own
        # pixel lies more than HIDDEN_DISTANCE from it (folded under, or
        # behind a hanging part): no estimator that reads this image can
        # place it, so the quality bar is on the visible ones.
        seen = priors.camera.back_project(uv_true, depth, mask)
        hidden = (seen - S).norm(dim=-1) > HIDDEN_DISTANCE
        out["keypoint_error_px"] = round((uv - uv_true).norm(dim=-1).mean().item(), 2)
        out["keypoint_error_mm"] = round(1000 * error.mean().item(), 2)
        out["keypoint_visible_fraction"] = round(1 - hidden.float().mean().item(), 4)
        out["keypoint_error_visible_mm"] = round(1000 * error[~hidden].mean().item(), 2)
        if hidden.any():
            out["keypoint_error_hidden_mm"] = round(
                1000 * error[hidden].mean().item(), 2
            )
    return out


def _plot(curves: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axs = plt.subplots(1, len(curves), figsize=(4 * len(curves), 3.2))
    for ax, (name, curve) in zip(np.atleast_1d(axs), curves.items(), strict=True):
        c = np.array(curve)
        ax.plot(np.arange(1, len(c) + 1), c[:, 0], label="train loss")
        ax.plot(
            np.arange(1, len(c) + 1),
            c[:, 1],
            label="val pixel error" if name == "f_R" else "val loss",
        )
        ax.set_title(name)
        ax.set_xlabel("epoch")
        ax.set_yscale("log")
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def train_priors(
    *, data: Path, out: Path, config: TrainConfig | None = None, progress: bool = True
) -> dict:
    """Trains the priors on the dataset `data`; writes `out`/priors.pt,
    metrics.json, curves.png. Returns the metrics summary."""
    cfg = config or TrainConfig()
    if cfg.epochs < 1 or cfg.keypoint_epochs < 0:
        raise InputError(f"epochs must be positive, got {cfg.epochs}")
    torch.manual_seed(cfg.seed)
    ds = LoadDataset(data)
    if len(ds) < 2:
        raise InputError(f"dataset {data} has too few transitions ({len(ds)})")
    camera_model = CameraModel.from_json(ds.camera)
    camera = PinholeCamera(camera_model)

    def log(msg: str) -> None:
        if progress:
            print(msg, file=sys.stderr, flush=True)

    wall0 = time.perf_counter()
    tr, va = _split(ds, cfg.holdout_fraction, cfg.seed)
    x_s, x_n, a = _dynamics_tensors(ds, tr)
    norms = {
        "state": Normalizer.fit(torch.cat([x_s, x_n])),
        "action": Normalizer.fit(a),
        "delta": Normalizer.fit(x_n - x_s),
    }
    config = {
        "num_keypoints": ds.num_keypoints,
        "image_size": list(ds.image_size),
        "camera": camera_model.to_json(),
        "keypoint_net": dc.asdict(cfg.keypoint_net)
        | {"num_keypoints": ds.num_keypoints},
        "train": {k: v for k, v in dc.asdict(cfg).items() if k != "keypoint_net"},
    }
    priors = build_priors(config, camera, norms)
    v_s, v_n, v_a = _dynamics_tensors(ds, va)
    enc = norms["state"].encode
    curves = {}
    curves["f_D"] = _fit_forward(priors, (x_s, x_n, a), (v_s, v_n, v_a), cfg, log)
    curves["f_I"] = _fit_mlp(
        priors.f_I,
        torch.cat([enc(x_s), enc(x_n)], -1),
        norms["action"].encode(a),
        torch.cat([enc(v_s), enc(v_n)], -1),
        norms["action"].encode(v_a),
        cfg,
        "f_I",
        log,
    )
    dyn_seconds = time.perf_counter() - wall0
    if cfg.keypoint_epochs:
        curves["f_R"] = _fit_keypoints(priors, ds, tr, va, cfg, log)
    for net in (priors.f_R, priors.f_D, priors.f_I):
        net.eval()
    metrics = evaluate(priors, ds, va)
    metrics["train_seconds"] = round(time.perf_counter() - wall0, 1)
    metrics["dynamics_train_seconds"] = round(dyn_seconds, 1)
    metrics["train_transitions"] = int(len(tr))
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    pick = np.random.default_rng(cfg.seed).choice(
        tr, size=min(PRIOR_STATES_KEPT, len(tr)), replace=False
    )
    priors.save(
        out,
        extra={
            "prior_states": torch.as_tensor(ds.arrays["keypoints"][np.sort(pick)]),
            "dataset_fingerprint": ds.fingerprint,
            "dataset_path": str(data),
            "metrics": metrics,
            "scenario_name": str(ds.attrs.get("scenario_name")),
            "code_version": str(ds.attrs.get("code_version")),
        },
    )
    (out / "metrics.json").write_text(json.dumps(metrics, indent=1))
    _plot(curves, out / "curves.png")
    return {"out": str(out), "dataset_fingerprint": ds.fingerprint, **metrics}


def _fit_forward(priors: Priors, train, val, cfg: TrainConfig, log) -> list:
    """Fits f_D on (states, next states, actions) tensors, in the priors'
    normalisation: the encoded state and action in, the encoded change out."""
    norms = priors.norms
    enc, enc_a, enc_d = (norms[k].encode for k in ("state", "action", "delta"))
    (x_s, x_n, a), (v_s, v_n, v_a) = train, val
    return _fit_mlp(
        priors.f_D,
        torch.cat([enc(x_s), enc_a(a)], -1),
        enc_d(x_n - x_s),
        torch.cat([enc(v_s), enc_a(v_a)], -1),
        enc_d(v_n - v_s),
        cfg,
        "f_D",
        log,
    )


def train_forward(
    *,
    data: list[Path],
    base: Path,
    out: Path,
    config: TrainConfig | None = None,
    progress: bool = True,
) -> dict:
    """Trains f_D again, from a fresh start, on the datasets `data` together
    (for example the prior scene's and a scene with an object, where the
    cloth meets it), keeping `base`'s f_R, f_I, normalisers and prior
    states; writes `out`/priors.pt, priors.json, metrics.json.

    Held out: the same fraction of each dataset's episodes. Returns the
    summary with f_D's held-out error per dataset, beside `base`'s f_D on
    the same transitions.
    """
    from fabric_imitation.learning.priors import load_priors

    cfg = config or TrainConfig()
    if cfg.epochs < 1:
        raise InputError(f"epochs must be positive, got {cfg.epochs}")
    if not data:
        raise InputError("train --forward-only needs at least one --data")
    old = load_priors(base)
    priors = copy.deepcopy(old)  # f_D learns afresh here; `old` keeps base's
    datasets = [LoadDataset(p, images=False) for p in data]
    for p, ds in zip(data, datasets, strict=True):
        if ds.num_keypoints != priors.num_keypoints:
            raise InputError(
                f"dataset {p} has {ds.num_keypoints} keypoints, the priors "
                f"{base} {priors.num_keypoints}"
            )
        if len(ds) < 2:
            raise InputError(f"dataset {p} has too few transitions ({len(ds)})")

    def log(msg: str) -> None:
        if progress:
            print(msg, file=sys.stderr, flush=True)

    wall0 = time.perf_counter()
    torch.manual_seed(cfg.seed)
    for module in priors.f_D.modules():
        if hasattr(module, "reset_parameters"):
            module.reset_parameters()
    parts = {"tr": [], "va": []}
    splits = []
    for ds in datasets:
        tr, va = _split(ds, cfg.holdout_fraction, cfg.seed)
        splits.append(va)
        for name, idx in (("tr", tr), ("va", va)):
            parts[name].append(_dynamics_tensors(ds, idx))
    x_s, x_n, a = (torch.cat(t) for t in zip(*parts["tr"], strict=True))
    v_s, v_n, v_a = (torch.cat(t) for t in zip(*parts["va"], strict=True))
    curve = _fit_forward(priors, (x_s, x_n, a), (v_s, v_n, v_a), cfg, log)
    priors.f_D.eval()
    held_out = []
    for p, ds, va in zip(data, datasets, splits, strict=True):
        new_m, old_m = evaluate(priors, ds, va), evaluate(old, ds, va)
        held_out.append(
            {
                "dataset": str(p),
                "fingerprint": ds.fingerprint,
                "scenario_name": str(ds.attrs.get("scenario_name")),
                "heldout_transitions": new_m["heldout_transitions"],
                "f_D_error_mm": new_m["f_D_error_mm"],
                "base_f_D_error_mm": old_m["f_D_error_mm"],
                "no_motion_baseline_mm": new_m["no_motion_baseline_mm"],
            }
        )
    metrics = dict(old.metadata.get("metrics", {}))
    metrics["f_D_held_out"] = held_out
    metrics["forward_train_seconds"] = round(time.perf_counter() - wall0, 1)
    metrics["forward_train_transitions"] = int(len(x_s))
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    extra = {
        k: v
        for k, v in old.metadata.items()
        if k not in ("config", "metrics") and not isinstance(v, torch.Tensor)
    }
    extra |= {
        "metrics": metrics,
        "forward_from": str(base),
        "forward_datasets": [
            {"path": str(p), "fingerprint": ds.fingerprint}
            for p, ds in zip(data, datasets, strict=True)
        ],
    }
    if old.prior_states is not None:
        extra["prior_states"] = old.prior_states
    priors.save(out, extra=extra)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=1))
    _plot({"f_D": curve}, out / "curves.png")
    return {"out": str(out), "f_D_held_out": held_out}
