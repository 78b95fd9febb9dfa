"""Where work runs: the one place that chooses a torch device.

A run trains on the GPU where torch sees one, else on the CPU; work done before the model
exists (the noise reading, the start's back-projection and filters) runs on the GPU where there
is one and the run was not asked for the CPU (:func:`run_on`), on the device of a tensor it is
given, or in numpy on the host (:data:`HOST`, a start begun while the launcher still imports
torch).  torch is imported only when a device is asked for.
"""

from __future__ import annotations

import contextlib

HOST = "host"
"""The device argument that keeps work in numpy on the host, without importing torch."""

CHOICES = ("auto", "cpu", "cuda")
"""What a user may ask for; ``auto`` is :func:`default_device`."""


_host_only = False
"""Set while a run asked for the CPU (:func:`run_on`): :func:`gpu` then answers None."""


def gpu():
    """The CUDA device if torch sees one and no CPU run is in progress (:func:`run_on`), else None."""
    if _host_only:
        return None
    import torch

    return torch.device("cuda") if torch.cuda.is_available() else None


@contextlib.contextmanager
def run_on(device: str):
    """Within: the helpers that choose their own device (:func:`work_device`, :func:`gpu`) keep
    off the GPU where the run's ``device`` is the CPU, so that a run asked for the CPU computes
    on the CPU alone, as it does on a machine without a GPU (and repeats to the bit as it does
    there).  Restores the previous choice on leaving."""
    global _host_only
    before = _host_only
    _host_only = str(device).split(":")[0] == "cpu"
    try:
        yield
    finally:
        _host_only = before


def default_device() -> str:
    """A run's device when none is asked for: ``cuda`` where torch sees a GPU, else ``cpu``
    (nerfstudio's own default, CUDA, stops a CPU-only machine at the model's first ``.to``)."""
    return "cuda" if gpu() is not None else "cpu"


def usable(device_type: str) -> bool:
    """Whether this machine's torch can run on ``device_type`` (``cpu``, ``cuda``, ``mps``)."""
    import torch

    if device_type == "cpu":
        return True
    if device_type == "cuda":
        return torch.cuda.is_available()
    if device_type == "mps":
        return torch.backends.mps.is_available()
    return False


def resolve(device: str) -> str:
    """``device`` (one of :data:`CHOICES`) as the device a run uses; ValueError naming it where
    it is not one of them or this machine cannot use it."""
    if device not in CHOICES:
        raise ValueError(f"device must be one of {CHOICES}, got {device!r}")
    if device == "auto":
        return default_device()
    if not usable(device):
        raise ValueError(f"device {device!r}: torch sees no CUDA device here; use device='cpu' or 'auto'")
    return device


def work_device(values, device=None):
    """Where work on ``values`` runs: ``device`` if given (:data:`HOST`: None, numpy on the host),
    else a tensor's own device off the CPU, else the GPU where there is one (None: numpy)."""
    if device == HOST:
        return None
    import torch

    if device is not None:
        return torch.device(device)
    if isinstance(values, torch.Tensor) and values.device.type != "cpu":
        return values.device
    return gpu()


def cores_given() -> int:
    """The cores this process may use: its affinity where the platform has one (a cluster's
    scheduler, ``taskset``), else the machine's."""
    import os

    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # no affinity on this platform
        return os.cpu_count() or 1


def threads_given() -> int:
    """The threads this process's work may spread over: :func:`cores_given`, at most the
    ``OMP_NUM_THREADS`` the environment sets (a batch scheduler's or a test runner's share:
    tasks given more threads than that contend with their neighbours for the same cores)."""
    import os

    cores = cores_given()
    try:
        limit = int(os.environ.get("OMP_NUM_THREADS", ""))
    except ValueError:  # unset or not a count: the cores decide
        return cores
    return max(1, min(cores, limit)) if limit > 0 else cores
