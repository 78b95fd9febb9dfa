"""CUDA's libraries loaded ahead of the fit that needs them.

A process's first use of each CUDA library torch calls into loads it and makes its handle:
cuFFT and cuSPARSE for the start's filtered back-projection, cuBLAS for the projector's and the
floors' matrix products, cuSOLVER for the floors' small solves, and the fused Adam and autograd
kernels.  On an H100, after ``import torch`` and the device's first use, these cost 60-260 ms
each (cold) against under 1 ms (warm), about 0.8 s in all, paid one after another on the run's
path.  :func:`load` makes each once, on tiny tensors; :func:`load_in_background` does it in a
thread while the launcher imports the engine and the start is computed, and the fit
:func:`wait` s for it before its first step (a CUDA graph's capture must not meet another
thread's allocations).  No result depends on it: the operations draw no random numbers and touch
no state a run reads.
"""

from __future__ import annotations

import threading

_loaded: set[str] = set()
_lock = threading.Lock()
_thread: threading.Thread | None = None


def load(device: str = "cuda") -> bool:
    """Load the CUDA libraries a fit uses on ``device`` (a CUDA device; another device, or a
    machine without one, does nothing).  Returns whether it loaded them now (False where they
    were loaded before, or there is nothing to load)."""
    import torch

    dev = torch.device(device)
    if dev.type != "cuda" or not torch.cuda.is_available():
        return False
    with _lock:
        if str(dev) in _loaded:
            return False
        _loaded.add(str(dev))
    with torch.cuda.device(dev):
        stream = torch.cuda.Stream(dev)  # beside, never in, the run's own stream
        with torch.cuda.stream(stream):
            _touch(dev)
        stream.synchronize()
    return True


def _touch(dev) -> None:
    import torch

    eye = torch.eye(8, device=dev)
    for dtype in (torch.float32, torch.float64):  # cuBLAS: the projector's products, the floors' moments
        a = eye.to(dtype)
        (a @ a).sum()
        torch.linalg.solve_ex(a[None] + a, a[None, :, :1])  # cuSOLVER: the floors' batched solve
    line = torch.ones(2, 16, dtype=torch.float64, device=dev)
    torch.fft.irfft(torch.fft.rfft(line, n=32, dim=-1), n=32, dim=-1)  # cuFFT: the start's filter
    sparse = torch.eye(4, device=dev).to_sparse_csr()
    sparse @ torch.ones(4, 2, device=dev)  # cuSPARSE: the start's back-projection
    torch.arange(64, device=dev, dtype=torch.float32).flip(0).sort()
    weight = torch.ones(4, 3, device=dev, requires_grad=True)
    optimiser = torch.optim.Adam([weight], lr=1e-3, fused=True)
    weight.exp().square().sum().backward()  # the autograd engine's device thread
    optimiser.step()


def load_in_background(device: str = "cuda") -> bool:
    """:func:`load` in a thread, started now; False where ``device`` is not a CUDA device torch
    can use.  Not a daemon: a process that exits while a daemon thread is inside a torch
    operation aborts (:mod:`gaussian_atoms_method.start_ahead`)."""
    global _thread
    import torch

    if torch.device(device).type != "cuda" or not torch.cuda.is_available():
        return False
    thread = threading.Thread(target=load, args=(device,), name="gaussian-atoms gpu libraries", daemon=False)
    thread.start()
    _thread = thread
    return True


def wait() -> None:
    """Return once a :func:`load_in_background` begun earlier has finished (at once where none
    was begun)."""
    thread = _thread
    if thread is not None:
        thread.join()
