"""The fit's CUDA kernels loaded in a thread while a process's first run imports and starts.

CUDA loads a kernel's module at its first use (lazy loading), and that first use waits for the
GPU's queued work.  On an H100 an operation family costs 10-100 ms cold (0.7 s for the 25 that
``scripts/studies/kernel_first_use.py`` times; 0.1-0.5 ms warm), paid one after another on the
way to the first steps.  :func:`begin`
runs each family once on a few elements in a thread, in the order the fit first uses them,
while the other threads import the engine and make the start; torch's operations release the
interpreter's lock, so they overlap.  The libraries that keep per-thread handles (cuBLAS,
cuSOLVER, cuSPARSE) and the optimiser are left to the fit: loaded from a second thread they
delayed the first ``ga.reconstruct`` by 0.6-0.8 s instead.

The warm-up touches only its own tensors and a private random generator, so a run's numbers do
not depend on it; a CUDA graph's capture waits for it (:func:`wait`: a launch from another
thread during a capture would break the capture).  Measured on one H100, Au noise 200, three
alternated pairs: ``gaussian-atoms train`` at its target 4.4-5.2 s from launch against 4.9-5.5 s
without (torch with CUDA's start 1.8-2.3 s there).
"""

from __future__ import annotations

import threading

_thread: threading.Thread | None = None
_devices: set[str] = set()


def begin(device: str) -> None:
    """Start loading the fit's kernels on ``device`` in a thread, once per process and CUDA
    device; nothing elsewhere (a CPU's kernels need no loading)."""
    global _thread
    if not str(device).startswith("cuda") or str(device) in _devices:
        return
    _devices.add(str(device))
    # Not a daemon: a process that exits while a daemon thread is inside a torch operation aborts.
    _thread = threading.Thread(target=_quietly, args=(str(device),), name="gaussian-atoms kernels", daemon=False)
    _thread.start()


def wait() -> None:
    """Return once the warm-up (if any) has launched all its operations."""
    if _thread is not None:
        _thread.join()


def _quietly(device: str) -> None:
    try:
        warm(device)
    except Exception:  # noqa: BLE001 - a warm-up that fails leaves the loading to the fit
        pass


def warm(device: str) -> None:
    """Run each operation family a fit uses once on a few elements of ``device``, in the order
    of their first use (the start's filters and peaks, the candidates' geometry, the density
    control, the noise model, the steps)."""
    import torch
    import torch.nn.functional as F

    with torch.no_grad():
        f = torch.tensor([3.0, 1.0, 2.0, 5.0], device=device)
        i = torch.tensor([0, 1, 1, 0], device=device)
        m = f > 2.0
        generator = torch.Generator(device=device).manual_seed(0)  # the fit's generators untouched
        f.neg(), f * 2, f + 1, f / 3, f - 1, torch.sort(f), torch.sort(i), f[i], f[m], f.mean(), f.var()
        F.pad(f.view(1, 1, 2, 2), (1, 1, 1, 1), mode="replicate"), F.pad(f, (1, 1))
        torch.arange(4, device=device), torch.arange(4.0, device=device)
        torch.div(f, 2.0, rounding_mode="floor"), torch.div(i, 2, rounding_mode="floor")
        torch.remainder(f, 2.0), torch.remainder(i, 2)
        f >= 1, f <= 1, i >= 1, m & m, torch.floor(f), torch.where(m, f, f), f.clamp(0, 1)
        torch.stack([f, f]), torch.cat([f, f]), 1 - f, f.flip(0), f.clone().add_(1), f.clone().neg_()
        f.clamp_min(0), f.pow(2), f.pow(0.5)
        F.max_pool3d(f.view(1, 1, 1, 2, 2), 1, 1, 0, return_indices=True)
        x = f.clone()
        x[m] = 0.0
        x.index_put_((i,), f, accumulate=True)
        m.nonzero(), f.min(), f.max(), f.max(0), f.sum(), i.sum(), i.cumsum(0), f.cumsum(0)
        torch.searchsorted(torch.sort(f)[0], f)
        torch.repeat_interleave(i + 1), torch.repeat_interleave(f, i + 1), f.index_select(0, i), f < 1, f.abs()
        torch.zeros(2, device=device).index_add_(0, i, f), m | m, ~m, f == 1, i == 1, torch.equal(f, f), m.all()
        f.log(), torch.rand(3, device=device, generator=generator), torch.linspace(0, 1, 5, device=device)
        f.cos(), f.sin(), f.reciprocal(), f.exp(), f.argmin()
        torch.randperm(5, device=device, generator=generator), f.sqrt(), torch.eye(3, device=device)
        f != 1, f.sgn(), m.any(), f.median(), f.std(), f.clamp_max(1)
        torch.zeros(2, device=device).scatter_reduce_(0, i, f, "amax", include_self=False)
        torch.linalg.vector_norm(f), m.clone().bitwise_and_(m), m.clone().bitwise_or_(m)
        torch.unique(i, return_inverse=True, return_counts=True)
        torch.diag_embed(f.view(2, 2)), torch.logsumexp(f, 0), f.amax(), f.double() * 2
