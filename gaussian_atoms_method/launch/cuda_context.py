"""CUDA's primary context made through the driver while a launcher imports torch.

torch makes the GPU's primary context at its first CUDA call, after its own import.  The
context is the driver's (``cuInit`` and ``cuDevicePrimaryCtxRetain`` in libcuda), torch's
runtime takes it as it finds it, and the driver's calls release the interpreter's lock: made in
a thread begun before ``import torch`` (Python on one core, seconds), it is ready when torch
asks for it.  On one H100, six alternated launches: CUDA was ready 0.03-0.05 s
after ``import torch`` returned, against 0.31-0.35 s without
(``scripts/studies/cuda_context_launch.py``).  No torch import here.
"""

from __future__ import annotations

import ctypes
import threading

LIBRARY = "libcuda.so.1"
"""NVIDIA's driver library (Linux); where it cannot be loaded nothing is begun."""

_thread: threading.Thread | None = None


def begin(ordinal: int = 0) -> None:
    """Retain the primary context of the driver's device ``ordinal`` (0: the device torch's
    ``cuda`` means, in the same order and under the same ``CUDA_VISIBLE_DEVICES``) in a thread,
    once per process.  A daemon: a driver that hangs must not hold the process at its exit."""
    global _thread
    if _thread is None:
        _thread = threading.Thread(target=_retain, args=(ordinal,), name="gaussian-atoms cuda context", daemon=True)
        _thread.start()


def _retain(ordinal: int) -> bool:
    try:
        driver = ctypes.CDLL(LIBRARY)
    except OSError:
        return False  # no NVIDIA driver: torch will find no GPU either
    device, context = ctypes.c_int(), ctypes.c_void_p()
    return (
        driver.cuInit(0) == 0
        and driver.cuDeviceGet(ctypes.byref(device), ordinal) == 0
        and driver.cuDevicePrimaryCtxRetain(ctypes.byref(context), device) == 0
    )
