"""The compiled polygon IoU kernel (`polygon_kernel.c`), built once per
machine with the system's C compiler into a cache and loaded with ctypes.

The shared library is named by a checksum of the source, the compiler
command and the platform, in the project's cache (learning/cache.py), so a
changed source builds a new one and nothing is rebuilt otherwise. Building
takes well under a second. Without a compiler (`$CC`, default `cc`) `Load`
returns None once with a warning, and callers use the torch code instead.
"""

import ctypes
import hashlib
import logging
import os
import platform
import shutil
import subprocess
import tempfile
from pathlib import Path

import torch
from fabric_imitation.learning.cache import CacheDir

SOURCE = Path(__file__).with_name("polygon_kernel.c")
# No -march=native: a cache shared by machines of one platform must run on
# all of them. No contraction into fused multiply-adds, so every machine
# rounds alike.
FLAGS = ["-O3", "-shared", "-fPIC", "-ffp-contract=off", "-std=c99"]

_log = logging.getLogger(__name__)
_LOADED: dict[str, object] = {}


def _build(cc: str, target: Path) -> None:
    target.parent.mkdir(parents=True, exist_ok=True)
    # Built under a temporary name and renamed: concurrent workers never see
    # half a library.
    fd, tmp = tempfile.mkstemp(dir=target.parent, suffix=".so.tmp")
    os.close(fd)
    try:
        subprocess.run(
            [cc, *FLAGS, "-o", tmp, str(SOURCE), "-lm"],
            check=True,
            capture_output=True,
            timeout=120,
        )
        os.replace(tmp, target)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def Load():
    """A function kernel(a, b, shift, out) that writes the IoU of every
    polygon of a (P, K, 2) with every polygon of b (W, L, 2) into out (P, W)
    (all contiguous float32 tensors), or None where it cannot be built."""
    if "kernel" in _LOADED:
        return _LOADED["kernel"]
    cc = os.environ.get("CC", "cc")
    kernel = None
    if shutil.which(cc) is None:
        _log.warning(
            "no C compiler (%s): the polygon IoU runs in torch, about 20x slower", cc
        )
    else:
        key = hashlib.sha256(
            SOURCE.read_bytes()
            + " ".join([cc, *FLAGS]).encode()
            + platform.platform().encode()
        ).hexdigest()[:16]
        target = CacheDir() / f"polygon_kernel-{key}.so"
        try:
            if not target.is_file():
                _build(cc, target)
            kernel = _Bind(ctypes.CDLL(str(target)))
        except (OSError, subprocess.SubprocessError) as e:
            _log.warning("polygon IoU kernel not built (%s): torch is used", e)
    _LOADED["kernel"] = kernel
    return kernel


def _Bind(library: ctypes.CDLL):
    fn = library.iou_all_pairs
    fn.restype = ctypes.c_int
    fn.argtypes = [
        ctypes.c_void_p,
        ctypes.c_int64,
        ctypes.c_int,
        ctypes.c_void_p,
        ctypes.c_int64,
        ctypes.c_int,
        ctypes.c_double,
        ctypes.c_double,
        ctypes.c_void_p,
    ]

    def kernel(a: torch.Tensor, b: torch.Tensor, shift, out: torch.Tensor) -> None:
        for t in (a, b, out):
            if t.dtype != torch.float32 or not t.is_contiguous():
                raise ValueError("the IoU kernel needs contiguous float32 tensors")
        if out.shape != (a.shape[0], b.shape[0]):
            raise ValueError(f"out must be {(a.shape[0], b.shape[0])}")
        status = fn(
            a.data_ptr(),
            a.shape[0],
            a.shape[1],
            b.data_ptr(),
            b.shape[0],
            b.shape[1],
            float(shift[0]),
            float(shift[1]),
            out.data_ptr(),
        )
        if status != 0:
            raise ValueError(
                f"the IoU kernel refused polygons of {a.shape[1]} and "
                f"{b.shape[1]} vertices (3 to 64)"
            )

    return kernel
