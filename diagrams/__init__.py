"""Diagram builders: the cloth station (simulated, Panda, hardware) and the
imitation diagram around it."""

import importlib.util

# PyTorch's CUDA wheels bring triton, which torch imports lazily (the first
# optimizer made imports torch._dynamo, which imports triton). Loading
# triton's native library for the first time after Drake's VTK renderer has
# drawn an image crashes the process (segfault with drake 1.58 and torch
# 2.14.1); loading it before any rendering is safe.
if importlib.util.find_spec("triton") is not None:
    import triton  # noqa: F401
