import atexit
import os
import shutil
import tempfile

import numpy as np
import pytest

# Tests run single-threaded and quietly; the machine has 2 cores.
os.environ.setdefault("OMP_NUM_THREADS", "1")
# The project's per-machine cache (compiled kernel, f_A per demo) is one of
# the session's own: tests neither read nor fill the user's.
_CACHE = tempfile.mkdtemp(prefix="fabric-imitation-cache-")
os.environ["FABRIC_IMITATION_CACHE"] = _CACHE
atexit.register(shutil.rmtree, _CACHE, ignore_errors=True)

# A coarse cloth keeps physics tests to seconds.
SMALL_CLOTH = "cloth: {resolution: [6, 6, 2], vbd: {resolution: [6, 6]}}\n"


def SmallCloth(engine: str) -> str:
    """SMALL_CLOTH on the given cloth engine (one `cloth` mapping: a second
    `cloth:` key would replace the first)."""
    return (
        f"cloth: {{engine: {engine}, resolution: [6, 6, 2], "
        "vbd: {resolution: [6, 6]}}\n"
    )


@pytest.fixture
def rng():
    return np.random.default_rng(0)
