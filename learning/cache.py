"""The per-machine cache of things this project builds or learns that are
fully determined by their inputs (the compiled polygon kernel, f_A for a
demo and priors), so they are made once per machine.

Location: `$FABRIC_IMITATION_CACHE`, else `$XDG_CACHE_HOME/fabric-imitation`,
else `~/.cache/fabric-imitation`. Deleting it only costs the time to make
its entries again. Entries are written under a temporary name and renamed,
so concurrent processes never read half an entry.
"""

import os
import tempfile
from collections.abc import Callable
from pathlib import Path


def cache_dir() -> Path:
    """Where this machine keeps the project's cached artefacts."""
    if os.environ.get("FABRIC_IMITATION_CACHE"):
        return Path(os.environ["FABRIC_IMITATION_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "fabric-imitation"


def write_atomically(path: Path, write: Callable[[str], None], suffix: str) -> None:
    """Calls write(tmp) on a temporary file beside `path`, then renames it to
    `path`; the temporary file is removed if write fails."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=suffix)
    os.close(fd)
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def read_torch(path: Path) -> dict | None:
    """The dict saved at `path` by `write_torch`, or None where there is none
    or it does not read (truncated, corrupt, another format)."""
    import torch

    if not path.is_file():
        return None
    try:
        saved = torch.load(path, weights_only=True)
    except Exception:  # noqa: BLE001 (any unreadable entry is made again)
        return None
    return saved if isinstance(saved, dict) else None


def write_torch(path: Path, obj: dict) -> None:
    """torch.save of `obj` to `path`, atomically."""
    import torch

    write_atomically(path, lambda tmp: torch.save(obj, tmp), ".tmp")
