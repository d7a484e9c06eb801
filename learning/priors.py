"""Trained priors as small batched predictors: `load_priors(path) -> Priors`
with `keypoints(mask, depth)`, `forward(S, A)`, `inverse(S, S_next)`.

States are (..., M, 3) in any frame whose z is height above the table (world
or an object frame); f_D and f_I work in each state's canonical frame
(learning/geometry.py), so the frame does not matter.
"""

import dataclasses as dc
from pathlib import Path

import numpy as np
import torch
from fabric_imitation.learning.checkpoint import (
    ReadTensorCheckpoint,
    WriteTensorCheckpoint,
)
from fabric_imitation.learning.errors import InputError
from fabric_imitation.learning.geometry import (
    PinholeCamera,
    canonical_frame,
    to_frame,
)
from fabric_imitation.learning.models import KeypointNet, KeypointNetConfig, Mlp
from fabric_imitation.learning.state import corner_indices

CHECKPOINT_FORMAT = "fabric-imitation-priors"
CHECKPOINT_VERSION = 2
# A checkpoint is a directory with two files: the description (format,
# network config, camera, metrics and the tensors file's sha256) in JSON, and
# the tensors alone in a torch file, loaded with `weights_only=True`, so a
# checkpoint cannot carry code (a pickled object is refused, not run).
CHECKPOINT_JSON = "priors.json"
# The shipped priors (with their policy, learning/policy.py).
DEFAULT_PRIORS = Path(__file__).resolve().parent / "priors" / "default"
CHECKPOINT_FILE = "priors.pt"
HEIGHT_SCALE = 4.0  # the height channel is metres * HEIGHT_SCALE
# Network -> (the normalisers of its two inputs, of its output).
FOLDED_NORMS = {
    "f_D": (("state", "action"), "delta"),
    "f_I": (("state", "state"), "action"),
}


@dc.dataclass
class Normalizer:
    mean: torch.Tensor
    std: torch.Tensor

    @classmethod
    def fit(cls, x: torch.Tensor) -> "Normalizer":
        return cls(x.mean(0), x.std(0).clamp_min(1e-4))

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.mean) / self.std

    def decode(self, y: torch.Tensor) -> torch.Tensor:
        return y * self.std + self.mean

    def state(self) -> dict:
        return {"mean": self.mean, "std": self.std}


def image_input(
    camera: PinholeCamera, mask: torch.Tensor, depth: torch.Tensor
) -> torch.Tensor:
    """(B, 2, H, W) network input from masks (B, H, W) and depths (B, H, W)."""
    on = (mask > 0).float()
    height = camera.height_map(depth).clamp(0.0, 1.0) * on * HEIGHT_SCALE
    return torch.stack([on, height], 1)


def canonical_inputs(S: torch.Tensor):
    origin, yaw = canonical_frame(S)
    return to_frame(S, origin, yaw), origin, yaw


class Priors:
    """f_R, f_D, f_I with their normalisation and camera, ready to predict."""

    def __init__(
        self,
        *,
        config: dict,
        f_R: KeypointNet,
        f_D: Mlp,
        f_I: Mlp,
        norms: dict[str, Normalizer],
        camera: PinholeCamera,
    ):
        self.config = config
        self.f_R, self.f_D, self.f_I = f_R.eval(), f_D.eval(), f_I.eval()
        self.norms = norms
        self.camera = camera
        # name -> (the weights' versions, FoldedMlp): see `_folded`.
        self._folded_cache: dict[str, tuple] = {}

    @property
    def num_keypoints(self) -> int:
        return int(self.config["num_keypoints"])

    @property
    def image_size(self) -> tuple[int, int]:
        return tuple(self.config["image_size"])

    # --- predictions -------------------------------------------------------

    @torch.no_grad()
    def keypoint_pixels(self, mask, depth) -> torch.Tensor:
        mask, depth = _batch_images(mask), _batch_images(depth)
        return self.f_R(image_input(self.camera, mask, depth))

    @torch.no_grad()
    def keypoints(self, mask, depth) -> np.ndarray:
        """World keypoints (B, M, 3) (or (M, 3) for one image) from fabric masks
        and depth images (metres) of this camera."""
        return self._keypoints(mask, depth, with_spread=False)[0]

    @torch.no_grad()
    def keypoints_and_spread(self, mask, depth) -> tuple[np.ndarray, np.ndarray]:
        """`keypoints` and f_R's spread of each, in pixels (B, M) (or (M,)):
        the standard deviation of its heatmap (KeypointNet.locate)."""
        return self._keypoints(mask, depth, with_spread=True)

    def _keypoints(self, mask, depth, *, with_spread: bool):
        single = np.ndim(mask) == 2
        mask_t, depth_t = _batch_images(mask), _batch_images(depth)
        if tuple(mask_t.shape[-2:]) != self.image_size:
            raise InputError(
                f"images are {tuple(mask_t.shape[-2:])}, the priors "
                f"were trained on {self.image_size}"
            )
        x = image_input(self.camera, mask_t, depth_t)
        spread = None
        if with_spread:
            uv, spread = self.f_R.locate(x)
            spread = spread.numpy()[0] if single else spread.numpy()
        else:
            uv = self.f_R(x)
        p = self.camera.back_project(uv, depth_t, mask_t).numpy()
        return (p[0] if single else p), spread

    @torch.no_grad()
    def forward(self, S, A) -> torch.Tensor:
        """f_D: next states (..., M, 3) after actions (..., 6)."""
        S = torch.as_tensor(S, dtype=torch.float32)
        A = torch.as_tensor(A, dtype=torch.float32)
        c, s, ox, oy = _canonical(S)
        Sc = _into(S, c, s, ox, oy)
        Ac = _rotate_moves(A, c, -s)
        x = torch.cat([Sc.flatten(-2), Ac], -1)
        delta = self._folded("f_D")(x).reshape(Sc.shape)
        return _out_of(Sc + delta, c, s, ox, oy)

    @torch.no_grad()
    def inverse(self, S, S_next) -> torch.Tensor:
        """f_I: actions (..., 6) that take S to S_next."""
        S = torch.as_tensor(S, dtype=torch.float32)
        S_next = torch.as_tensor(S_next, dtype=torch.float32)
        c, s, ox, oy = _canonical(S)
        x = torch.cat(
            [
                _into(S, c, s, ox, oy).flatten(-2),
                _into(S_next, c, s, ox, oy).flatten(-2),
            ],
            -1,
        )
        return _rotate_moves(self._folded("f_I")(x), c, s)

    def _folded(self, name: str) -> "FoldedMlp":
        """The MLP `name` with its input and output normalisers folded into
        its first and last layers (the same function, fewer operations),
        rebuilt whenever its weights have changed (training)."""
        net = getattr(self, name)
        key = tuple((id(p), p._version) for p in net.parameters())
        cached = self._folded_cache.get(name)
        if cached is None or cached[0] != key:
            inputs, output = FOLDED_NORMS[name]
            mean = torch.cat([self.norms[k].mean for k in inputs], -1)
            std = torch.cat([self.norms[k].std for k in inputs], -1)
            cached = (key, FoldedMlp(net, mean, std, self.norms[output]))
            self._folded_cache[name] = cached
        return cached[1]

    # --- checkpoint --------------------------------------------------------

    def save(self, directory: Path, *, extra: dict) -> Path:
        """Writes `directory`/priors.pt (tensors) and priors.json (the rest:
        config, and `extra`'s JSON values; its tensors go to priors.pt).
        Returns the JSON path. Both files appear whole or not at all."""
        tensors = {}
        for name in ("f_R", "f_D", "f_I"):
            for key, value in getattr(self, name).state_dict().items():
                tensors[f"{name}.{key}"] = value.detach().cpu().contiguous()
        for name, norm in self.norms.items():
            tensors[f"norms.{name}.mean"] = norm.mean.detach().cpu().contiguous()
            tensors[f"norms.{name}.std"] = norm.std.detach().cpu().contiguous()
        metadata = {}
        for key, value in extra.items():
            if isinstance(value, torch.Tensor):
                tensors[key] = value.detach().cpu().contiguous()
            else:
                metadata[key] = value
        return WriteTensorCheckpoint(
            directory,
            json_name=CHECKPOINT_JSON,
            tensors_name=CHECKPOINT_FILE,
            tensors=tensors,
            description={
                "format": CHECKPOINT_FORMAT,
                "version": CHECKPOINT_VERSION,
                "config": self.config,
                "norms": sorted(self.norms),
                "metadata": metadata,
            },
        )


class FoldedMlp:
    """An Mlp of (x - mean) / std whose output is decoded by `out`, as one
    MLP with the normalisation folded into its first and last layers."""

    def __init__(self, net: Mlp, mean, std, out: Normalizer):
        linear = [m for m in net.net if isinstance(m, torch.nn.Linear)]
        self.layers = [(m.weight.detach(), m.bias.detach()) for m in linear]
        W, b = self.layers[0]
        W = W / std
        self.layers[0] = (W, b - W @ mean)
        W, b = self.layers[-1]
        self.layers[-1] = (W * out.std[:, None], b * out.std + out.mean)

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        *hidden, (W, b) = self.layers
        for Wh, bh in hidden:
            x = torch.nn.functional.linear(x, Wh, bh).relu_()
        return torch.nn.functional.linear(x, W, b)


def _canonical(S: torch.Tensor):
    """Cosine, sine of the yaw and x, y of the origin (each (...)) of the
    canonical frame of states S (..., M, 3) (geometry.canonical_frame's
    frame, its yaw kept as the unit vector along s2 - s1)."""
    idx = corner_indices(S.shape[-2])
    s1, s2 = S[..., idx["s1"], :2], S[..., idx["s2"], :2]
    o = (s1 + s2) / 2
    d = s2 - s1
    n = d.norm(dim=-1)
    ok = n > 0
    c = torch.where(ok, d[..., 0] / torch.where(ok, n, 1.0), 1.0)
    s = torch.where(ok, d[..., 1] / torch.where(ok, n, 1.0), 0.0)
    return c, s, o[..., 0], o[..., 1]


def _into(P, c, s, ox, oy) -> torch.Tensor:
    """Points (..., K, 3) into the frame (c, s, ox, oy) of `_canonical`."""
    x = P[..., 0] - ox[..., None]
    y = P[..., 1] - oy[..., None]
    c, s = c[..., None], s[..., None]
    return torch.stack([c * x + s * y, c * y - s * x, P[..., 2]], -1)


def _out_of(P, c, s, ox, oy) -> torch.Tensor:
    """Points (..., K, 3) from the frame (c, s, ox, oy) back to its parent."""
    x, y = P[..., 0], P[..., 1]
    cc, ss = c[..., None], s[..., None]
    return torch.stack(
        [cc * x - ss * y + ox[..., None], ss * x + cc * y + oy[..., None], P[..., 2]],
        -1,
    )


def _rotate_moves(A, c, s) -> torch.Tensor:
    """Actions (..., 6) (two moves) rotated by the yaw of (c, s)."""
    m = A.reshape(*A.shape[:-1], 2, 3)
    cc, ss = c[..., None], s[..., None]
    x, y = m[..., 0], m[..., 1]
    return torch.stack([cc * x - ss * y, ss * x + cc * y, m[..., 2]], -1).reshape(
        A.shape
    )


def _batch_images(x) -> torch.Tensor:
    t = torch.as_tensor(np.array(x, dtype=np.float32))
    return t[None] if t.ndim == 2 else t


def build_priors(config: dict, camera: PinholeCamera, norms: dict) -> Priors:
    m = int(config["num_keypoints"])
    kp_config = KeypointNetConfig(**config["keypoint_net"])
    if kp_config.num_keypoints != m:
        raise InputError("checkpoint config disagrees on the number of keypoints")
    return Priors(
        config=config,
        f_R=KeypointNet(kp_config),
        f_D=Mlp(3 * m + 6, 3 * m),
        f_I=Mlp(6 * m, 6),
        norms=norms,
        camera=camera,
    )


def load_priors(
    path: Path | str,
    *,
    num_keypoints: int | None = None,
    image_size: tuple[int, int] | None = None,
    camera=None,
) -> Priors:
    """Loads priors from a checkpoint directory (or a file in it).

    Args:
        num_keypoints, image_size, camera: when given, the checkpoint must
            match them (a CameraModel's intrinsics and pose).

    Raises:
        InputError: missing or corrupt file, another format or version, a
            checksum mismatch, a tensors file that needs pickle, a mismatch.
    """
    description, tensors, file = ReadTensorCheckpoint(
        path,
        json_name=CHECKPOINT_JSON,
        tensors_name=CHECKPOINT_FILE,
        fmt=CHECKPOINT_FORMAT,
        version=CHECKPOINT_VERSION,
        what="priors",
        retrain="retrain with `fabric-imitate train`",
    )
    tensors_file = file.parent / description["tensors"]["file"]
    blob = {
        "config": description["config"],
        "norms": {
            name: {
                "mean": tensors.get(f"norms.{name}.mean"),
                "std": tensors.get(f"norms.{name}.std"),
            }
            for name in description["norms"]
        },
        **{
            net: {
                k[len(net) + 1 :]: v
                for k, v in tensors.items()
                if k.startswith(net + ".")
            }
            for net in ("f_R", "f_D", "f_I")
        },
        **description["metadata"],
        "prior_states": tensors.get("prior_states"),
    }
    config = blob["config"]
    if num_keypoints is not None and int(config["num_keypoints"]) != num_keypoints:
        raise InputError(
            f"priors {file} predict {config['num_keypoints']} keypoints, "
            f"the scenario uses {num_keypoints}"
        )
    if image_size is not None and tuple(config["image_size"]) != tuple(image_size):
        raise InputError(
            f"priors {file} were trained on {tuple(config['image_size'])} "
            f"images, the camera gives {tuple(image_size)}"
        )
    from fabric_imitation.learning.demo_io import CameraModel

    stored = CameraModel.from_json(config["camera"])
    if camera is not None and not stored.same_as(camera):
        raise InputError(
            f"priors {file} were trained with another camera "
            "(intrinsics or pose differ)"
        )
    if any(v["mean"] is None or v["std"] is None for v in blob["norms"].values()):
        raise InputError(f"priors {tensors_file} lack a normaliser's tensors")
    norms = {k: Normalizer(v["mean"], v["std"]) for k, v in blob["norms"].items()}
    priors = build_priors(config, PinholeCamera(stored), norms)
    try:
        for name in ("f_R", "f_D", "f_I"):
            getattr(priors, name).load_state_dict(blob[name])
    except (RuntimeError, KeyError) as e:
        raise InputError(
            f"priors {file} do not fit the networks: {' '.join(str(e).split())[:150]}"
        ) from None
    priors.metadata = {
        k: v
        for k, v in blob.items()
        if k not in ("f_R", "f_D", "f_I", "norms", "prior_states")
    }
    priors.prior_states = blob.get("prior_states")
    return priors
