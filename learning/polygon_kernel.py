"""The compiled polygon IoU kernel (`polygon_kernel.c`), built once per
machine with the system's C compiler into the project's cache
(learning/cache.py) and loaded with ctypes.

The shared library is named by a checksum of the source, the compiler
command and the platform, so a changed source builds a new one and nothing
is rebuilt otherwise. Building takes well under a second. Without a
compiler (`$CC`, default `cc`) `load` returns None, once with a warning,
and callers use the torch code instead.
"""

import ctypes
import hashlib
import logging
import os
import platform
import shutil
import subprocess
from collections.abc import Callable
from pathlib import Path

import torch
from fabric_imitation.learning.cache import cache_dir, write_atomically

SOURCE = Path(__file__).with_name("polygon_kernel.c")
# No -march=native: a cache shared by machines of one platform must run on
# all of them. No contraction into fused multiply-adds, so every machine
# rounds alike.
FLAGS = ["-O3", "-shared", "-fPIC", "-ffp-contract=off", "-std=c99"]
# Vertices per polygon the kernel takes (MAX_VERTICES in the C source).
MAX_VERTICES = 64

Kernel = Callable[[torch.Tensor, torch.Tensor, tuple, torch.Tensor], None]

_log = logging.getLogger(__name__)
_LOADED: dict[str, Kernel | None] = {}


def _build(cc: str, target: Path) -> None:
    def compile_to(tmp: str) -> None:
        try:
            subprocess.run(
                [cc, *FLAGS, "-o", tmp, str(SOURCE), "-lm"],
                check=True,
                capture_output=True,
                text=True,
                timeout=120,
            )
        except subprocess.CalledProcessError as e:
            raise OSError(f"{cc} failed: {e.stderr.strip()[-500:]}") from e

    write_atomically(target, compile_to, ".so.tmp")


def load() -> Kernel | None:
    """A function kernel(a, b, shift, out) that writes the IoU of every
    polygon of a (P, K, 2) with every polygon of b (W, L, 2) into out (P, W)
    (contiguous float32 CPU tensors, 3 <= K, L <= MAX_VERTICES), or None
    where it cannot be built. Loaded once per process (`forget` drops it)."""
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
        target = cache_dir() / f"polygon_kernel-{key}.so"
        for attempt in range(2):
            try:
                if not target.is_file():
                    _build(cc, target)
                kernel = _bind(ctypes.CDLL(str(target)))
                break
            except (OSError, subprocess.SubprocessError) as e:
                # A library that does not load (truncated, another machine's)
                # is built once more.
                if attempt == 0 and target.is_file():
                    target.unlink(missing_ok=True)
                    continue
                _log.warning("polygon IoU kernel not built (%s): torch is used", e)
    _LOADED["kernel"] = kernel
    return kernel


def forget() -> None:
    """Drops the loaded kernel, so the next `load` looks again (after the
    cache directory or the compiler changed)."""
    _LOADED.clear()


def _bind(library: ctypes.CDLL) -> Kernel:
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
            if t.dtype != torch.float32 or not t.is_contiguous() or t.is_cuda:
                raise ValueError("the IoU kernel needs contiguous float32 CPU tensors")
        if a.dim() != 3 or b.dim() != 3 or a.shape[-1] != 2 or b.shape[-1] != 2:
            raise ValueError(
                f"the IoU kernel needs (P, K, 2) and (W, L, 2), got "
                f"{tuple(a.shape)} and {tuple(b.shape)}"
            )
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
        if status == 1:
            raise ValueError(
                f"the IoU kernel takes polygons of 3 to {MAX_VERTICES} vertices, "
                f"got {a.shape[1]} and {b.shape[1]}"
            )
        if status != 0:
            raise MemoryError("the IoU kernel could not allocate its buffers")

    return kernel
