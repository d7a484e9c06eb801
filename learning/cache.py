"""The per-machine cache of things this project builds or learns that are
fully determined by their inputs (the compiled polygon kernel, f_A for a
demo and priors), so they are made once per machine.

Location: `$FABRIC_IMITATION_CACHE`, else `$XDG_CACHE_HOME/fabric-imitation`,
else `~/.cache/fabric-imitation`. Deleting it only costs the time to make
its entries again.
"""

import os
from pathlib import Path


def CacheDir() -> Path:
    """Where this machine keeps the project's cached artefacts."""
    if os.environ.get("FABRIC_IMITATION_CACHE"):
        return Path(os.environ["FABRIC_IMITATION_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "fabric-imitation"
