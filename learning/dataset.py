"""The prior dataset: transitions (O, S, A, O', S') from the contact-free scene.

Storage is one HDF5 file (chunked, gzip) at PATH. Collection writes each
finished episode as its own shard, atomically, into PATH.parts/; consolidation
merges the contiguous run of episodes into a new PATH (written to a temporary
file, then renamed) and deletes the merged shards. A process killed at any
moment therefore loses at most the episodes in flight and never leaves a
half-written PATH; rerunning resumes from the shards and PATH.

Per transition: mask, mask_next (H, W) uint8; depth, depth_next (H, W) uint16
in 0.1 mm (0 = no return); keypoints, keypoints_next (M, 3) float32 world;
action (6,) float32; grippers, grippers_next (2, 3) float32; episode, step;
rejected (candidate actions rejected before the applied one).
"""

import contextlib
import dataclasses as dc
import hashlib
import json
import os
import re
from pathlib import Path

import h5py
import numpy as np
from fabric_imitation.learning.errors import InputError

DATASET_FORMAT = "fabric-imitation-prior"
DATASET_VERSION = 1
DEPTH_UNIT = 1e-4  # metres per uint16 depth count
FIELDS = (
    "mask",
    "mask_next",
    "depth",
    "depth_next",
    "keypoints",
    "keypoints_next",
    "action",
    "grippers",
    "grippers_next",
    "episode",
    "step",
    "rejected",
)
_SHARD = re.compile(r"episode_(\d{7})\.npz$")


def EncodeDepth(depth_m: np.ndarray) -> np.ndarray:
    d = np.where(np.isfinite(depth_m), depth_m, 0.0)
    return np.clip(np.round(d / DEPTH_UNIT), 0, 65535).astype(np.uint16)


def DecodeDepth(depth_u16: np.ndarray) -> np.ndarray:
    d = depth_u16.astype(np.float32) * DEPTH_UNIT
    return np.where(depth_u16 == 0, np.inf, d).astype(np.float32)


def PartsDir(path: Path) -> Path:
    path = Path(path)
    return path.with_name(path.name + ".parts")


def ShardPath(path: Path, episode: int) -> Path:
    return PartsDir(path) / f"episode_{episode:07d}.npz"


def WriteShard(path: Path, episode: int, arrays: dict[str, np.ndarray]) -> None:
    """Writes one episode's transitions atomically (temp file + rename)."""
    target = ShardPath(path, episode)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_name(target.name + f".partial-{os.getpid()}.npz")
    np.savez(tmp, **arrays)
    os.replace(tmp, target)


def ShardEpisodes(path: Path) -> dict[int, Path]:
    parts = PartsDir(path)
    if not parts.is_dir():
        return {}
    out = {}
    for f in parts.iterdir():
        m = _SHARD.search(f.name)
        if m:
            out[int(m.group(1))] = f
    return out


def _read_shard(f: Path) -> dict[str, np.ndarray] | None:
    try:
        with np.load(f) as z:
            if len(z["action"]) == 0:
                return {"action": z["action"]}
            return {k: z[k] for k in FIELDS}
    except Exception:  # noqa: BLE001 (a damaged shard is recomputed)
        return None


@dc.dataclass
class DatasetInfo:
    num_transitions: int
    num_episodes: int  # episodes 0..num_episodes-1 are in the file
    complete: bool
    attrs: dict


def ReadInfo(path: Path) -> DatasetInfo | None:
    """Header of an existing dataset file; None if the file does not exist."""
    path = Path(path)
    if not path.exists():
        return None
    try:
        with h5py.File(path, "r") as f:
            attrs = dict(f.attrs)
            return DatasetInfo(
                int(attrs["num_transitions"]),
                int(attrs["num_episodes"]),
                bool(attrs["complete"]),
                attrs,
            )
    except (OSError, KeyError) as e:
        raise InputError(
            f"dataset {path} is corrupt or not a prior dataset: "
            f"{' '.join(str(e).split())}"
        ) from None


def Fingerprint(keypoints: np.ndarray, action: np.ndarray, episode: np.ndarray) -> str:
    h = hashlib.sha256()
    for a in (keypoints, action, episode):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:16]


def Consolidate(path: Path, *, target: int, metadata: dict) -> DatasetInfo | None:
    """Merges PATH and the contiguous shards after it into a new PATH holding at
    most `target` transitions; deletes the merged shards.

    `metadata` (scenario, seed, camera, code version, ...) is stored as
    attributes and must match an existing PATH's.
    """
    path = Path(path)
    info = ReadInfo(path)
    chunks: dict[str, list[np.ndarray]] = {k: [] for k in FIELDS}
    if info is not None:
        _check_metadata(path, info.attrs, metadata)
        with h5py.File(path, "r") as f:
            for k in FIELDS:
                chunks[k].append(f[k][:])
    next_episode = info.num_episodes if info is not None else 0
    total = info.num_transitions if info is not None else 0
    shards = ShardEpisodes(path)
    merged = []
    while total < target and next_episode in shards:
        data = _read_shard(shards[next_episode])
        if data is None:  # damaged: leave it out; the collector redoes it
            shards[next_episode].unlink(missing_ok=True)
            break
        n = min(len(data["action"]), target - total)
        if n > 0:
            for k in FIELDS:
                chunks[k].append(data[k][:n])
        total += n
        merged.append(shards[next_episode])
        next_episode += 1
    if not merged:
        return info
    arrays = {k: np.concatenate(v) if v else None for k, v in chunks.items()}
    complete = total >= target
    tmp = path.with_name(path.name + f".partial-{os.getpid()}")
    path.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(tmp, "w") as f:
        for k, a in arrays.items():
            chunk = (min(64, max(1, len(a))),) + a.shape[1:]
            f.create_dataset(
                k,
                data=a,
                maxshape=(None,) + a.shape[1:],
                chunks=chunk,
                compression="gzip",
                compression_opts=4,
                shuffle=True,
            )
        attrs = {
            **metadata,
            "format": DATASET_FORMAT,
            "version": DATASET_VERSION,
            "num_transitions": total,
            "num_episodes": next_episode,
            "target_transitions": target,
            "complete": complete,
            "fingerprint": Fingerprint(
                arrays["keypoints"], arrays["action"], arrays["episode"]
            ),
        }
        for k, v in attrs.items():
            f.attrs[k] = v
    os.replace(tmp, path)
    for shard in merged:
        shard.unlink(missing_ok=True)
    if complete:  # shards past the target are not needed
        for shard in ShardEpisodes(path).values():
            shard.unlink(missing_ok=True)
        with contextlib.suppress(OSError):
            PartsDir(path).rmdir()
    return ReadInfo(path)


_MATCHED_KEYS = ("scenario_yaml", "seed", "camera")


def _check_metadata(path: Path, attrs: dict, metadata: dict) -> None:
    for k in _MATCHED_KEYS:
        if k in metadata and str(attrs.get(k)) != str(metadata[k]):
            raise InputError(
                f"dataset {path} was collected with another {k}; use "
                "another --out or the same settings"
            )


@dc.dataclass
class PriorDataset:
    """A loaded, checked prior dataset (all in memory)."""

    path: Path
    attrs: dict
    arrays: dict[str, np.ndarray]

    def __len__(self) -> int:
        return len(self.arrays["action"])

    @property
    def camera(self) -> dict:
        return json.loads(self.attrs["camera"])

    @property
    def fingerprint(self) -> str:
        return str(self.attrs["fingerprint"])

    @property
    def num_keypoints(self) -> int:
        return int(self.arrays["keypoints"].shape[1])

    @property
    def image_size(self) -> tuple[int, int]:
        return tuple(self.arrays["mask"].shape[1:])


def LoadDataset(path: Path | str, *, images: bool = True) -> PriorDataset:
    """Loads a prior dataset and checks it.

    Raises:
        InputError: missing, truncated or corrupt file, another format, an
            empty or incomplete dataset, NaN in a transition.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"dataset not found: {path}")
    try:
        with h5py.File(path, "r") as f:
            attrs = dict(f.attrs)
            if attrs.get("format") != DATASET_FORMAT:
                raise InputError(f"{path} is not a {DATASET_FORMAT} file")
            names = (
                FIELDS
                if images
                else tuple(k for k in FIELDS if not k.startswith(("mask", "depth")))
            )
            arrays = {k: f[k][:] for k in names}
    except OSError as e:
        raise InputError(
            f"dataset {path} is corrupt or truncated: {' '.join(str(e).split())[:200]}"
        ) from None
    except KeyError as e:
        raise InputError(f"dataset {path} lacks the field {e}") from None
    n = len(arrays["action"])
    if n == 0:
        raise InputError(f"dataset {path} is empty")
    if any(len(a) != n for a in arrays.values()):
        raise InputError(f"dataset {path} is truncated: fields have different lengths")
    for k in ("keypoints", "keypoints_next", "action", "grippers", "grippers_next"):
        bad = ~np.isfinite(arrays[k]).all(axis=tuple(range(1, arrays[k].ndim)))
        if bad.any():
            raise InputError(
                f"dataset {path}: NaN or inf in {k} of transition "
                f"{int(np.flatnonzero(bad)[0])}"
            )
    return PriorDataset(path=path, attrs=attrs, arrays=arrays)
