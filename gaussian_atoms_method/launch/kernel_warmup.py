"""The fit's CUDA kernels loaded in a thread while a process's first run imports and starts.

CUDA loads a kernel's module at its first use (lazy loading), and that first use waits for the
GPU's queued work (``scripts/studies/kernel_first_use.py``), paid one family after another on
the way to the first steps.  :func:`begin` runs each family the fit uses once on a few elements in a thread, in the
order of their first use, while the other threads import the engine and make the start (torch's
operations release the interpreter's lock).  Where the GPU stays idle meanwhile the libraries'
first calls can come first (``libraries_first``, :func:`libraries`); beside the train start,
which uses the GPU at once, they slowed the run, so there the fit makes them.

The warm-up touches only its own tensors and a private random generator, so a run's numbers do
not depend on it; a CUDA graph's capture waits for it (:func:`wait`: a launch from another
thread during a capture would break the capture).  On one H100, Au noise 200, three alternated
pairs: ``gaussian-atoms train`` reached its target 4.4-5.2 s from launch against 4.9-5.5 s
without it.
"""

from __future__ import annotations

import threading
from contextlib import nullcontext

from gaussian_atoms_method.launch.handover import quick_handover

_threads: dict[str, threading.Thread] = {}  # device -> its warm-up, one per process


def begin(device: str, libraries_first: bool = False, handover: bool = False) -> None:
    """Start loading the fit's kernels on ``device`` in a thread, once per process and CUDA
    device; nothing elsewhere (a CPU's kernels need no loading).  ``libraries_first``: the
    libraries' first calls too (:func:`libraries`), where the GPU stays idle while the warm-up
    begins (beside ``ga.reconstruct``'s imports; beside the train start, which uses the GPU at
    once, they slowed it).  ``handover``: the thread runs under
    :func:`~gaussian_atoms_method.launch.handover.quick_handover`, which changes the
    interpreter's switch interval while it runs: for a launcher's own process only, never a
    user's."""
    device = str(device)
    if not device.startswith("cuda") or device in _threads:
        return
    parts = (libraries, warm) if libraries_first else (warm,)
    # Not a daemon: a process that exits while a daemon thread is inside a torch operation aborts.
    _threads[device] = threading.Thread(target=_quietly, args=(device, parts, handover), name="gaussian-atoms kernels")
    _threads[device].start()


def wait() -> None:
    """Return once every warm-up begun has launched all its operations."""
    for thread in list(_threads.values()):
        thread.join()


def _quietly(device: str, parts, handover: bool) -> None:
    # a launcher's own process: beside the imports each operation gets the lock back quickly
    with quick_handover() if handover else nullcontext():
        for part in parts:
            try:
                part(device)
            except Exception:  # noqa: BLE001 - a warm-up that fails leaves the loading to the fit
                pass


def libraries(device: str) -> None:
    """The first calls of the libraries the fit uses before its first steps: cuBLAS (the FBP's
    filter and the kernel's matrices), cuSPARSE (the back-projection), cuSOLVER (the floors'
    solve) and Adam's fused update, in float32 and float64.  Adam's update is called as the
    kernel itself: the stock optimiser's first step imports torch's compiler front end."""
    import torch

    with torch.no_grad():
        for dtype in (torch.float32, torch.float64):
            a = torch.ones(2, 3, 3, device=device, dtype=dtype)
            a @ a, a[0] @ a[0], a[0] @ a[0, 0]
            indices = torch.tensor([[0, 1, 2], [0, 1, 2]], device=device)  # COO: CSR construction warns "beta"
            torch.sparse.mm(torch.sparse_coo_tensor(indices, a[0, 0], (3, 3), check_invariants=False), a[0])
            torch.linalg.solve_ex(a + 2 * torch.eye(3, device=device, dtype=dtype), a[..., :1])
        p = [torch.ones(3, device=device)]
        torch._foreach_add_([torch.zeros((), device=device)], 1)
        torch._fused_adam_(
            p, [torch.ones(3, device=device)], [torch.zeros(3, device=device)], [torch.zeros(3, device=device)], [],
            [torch.ones((), device=device)], lr=1e-3, beta1=0.9, beta2=0.999, weight_decay=0.0, eps=1e-8,
            amsgrad=False, maximize=False,
        )  # fmt: skip


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
