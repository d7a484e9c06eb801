"""Checkpoints that cannot run code: a JSON description plus a torch file of
tensors only, loaded with `weights_only=True` (a pickled object is refused,
not run), with the tensors file's sha256 in the description and, where the
directory has a manifest.json (shipped checkpoints), every listed file's.

Used by the priors (learning/priors.py) and the baselines
(learning/baselines.py)."""

import json
import pickle
from pathlib import Path

import torch
from fabric_imitation.learning.demo_io import FileSha256
from fabric_imitation.learning.errors import InputError


def WriteTensorCheckpoint(
    directory: Path,
    *,
    json_name: str,
    tensors_name: str,
    tensors: dict[str, torch.Tensor],
    description: dict,
) -> Path:
    """Writes `directory`/`tensors_name` and `json_name` (the description
    with "tensors": {file, sha256} added). Both files appear whole or not at
    all. Returns the JSON path."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / tensors_name
    tmp = path.with_name(path.name + ".partial")
    torch.save({k: v.detach().cpu().contiguous() for k, v in tensors.items()}, tmp)
    description = {
        **description,
        "tensors": {"file": tensors_name, "sha256": FileSha256(tmp)},
    }
    json_path = directory / json_name
    json_tmp = json_path.with_name(json_path.name + ".partial")
    json_tmp.write_text(json.dumps(description, indent=1, default=lambda o: o.item()))
    tmp.replace(path)
    json_tmp.replace(json_path)
    return json_path


def ReadTensorCheckpoint(
    path: Path | str,
    *,
    json_name: str,
    tensors_name: str,
    fmt: str,
    version: int,
    what: str,
    retrain: str,
) -> tuple[dict, dict[str, torch.Tensor], Path]:
    """(description, tensors, JSON path) of the checkpoint in directory
    `path` (or the directory of the file `path`).

    Raises:
        InputError (one line, naming `what` and the file): missing or
            corrupt file, another format or version, a checksum mismatch, a
            tensors file that needs pickle; `retrain` says how to make one.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"{what} checkpoint not found: {path}")
    directory = path if path.is_dir() else path.parent
    file = directory / json_name
    if not file.is_file():
        if (directory / tensors_name).is_file():
            raise InputError(
                f"{what} {directory} have no {json_name}: an old pickled "
                f"checkpoint, not loaded because unpickling can run code; "
                f"{retrain}"
            )
        raise InputError(f"{what} checkpoint not found: {file}")
    try:
        description = json.loads(file.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError):
        raise InputError(f"{what} checkpoint {file} is corrupt (not JSON)") from None
    if (
        not isinstance(description, dict)
        or description.get("format") != fmt
        or description.get("version") != version
    ):
        raise InputError(f"{file} is not a {fmt} checkpoint of version {version}")
    manifest = directory / "manifest.json"
    if manifest.is_file():  # shipped checkpoints list their files' checksums
        try:
            listed = json.loads(manifest.read_text()).get("files", {})
        except (json.JSONDecodeError, UnicodeDecodeError, AttributeError):
            raise InputError(f"{what} {manifest} is corrupt") from None
        for name, digest in listed.items():
            f = directory / name
            if name in (json_name, tensors_name) and (
                not f.is_file() or FileSha256(f) != digest
            ):
                raise InputError(
                    f"{what} {f} is missing, truncated or changed (checksum "
                    f"mismatch with {manifest.name})"
                )
    tensors_file = directory / description["tensors"]["file"]
    if not tensors_file.is_file():
        raise InputError(f"{what} checkpoint {file}: {tensors_file.name} is missing")
    if FileSha256(tensors_file) != description["tensors"]["sha256"]:
        raise InputError(
            f"{what} {tensors_file} is truncated or changed (checksum mismatch)"
        )
    try:
        tensors = torch.load(tensors_file, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:
        raise InputError(
            f"{what} {tensors_file} hold more than tensors (refused: loading "
            f"them would need pickle, which can run code): "
            f"{' '.join(str(e).split())[:100]}"
        ) from None
    except Exception as e:  # noqa: BLE001 (any other failure is a bad file)
        raise InputError(
            f"{what} checkpoint {tensors_file} is corrupt: "
            f"{' '.join(str(e).split())[:150]}"
        ) from None
    if not isinstance(tensors, dict) or not all(
        isinstance(v, torch.Tensor) for v in tensors.values()
    ):
        raise InputError(f"{what} {tensors_file} is not a dictionary of tensors")
    return description, tensors, file
