"""The start of a run (:func:`~gaussian_atoms_method.atoms.initialise.compute_start`: the noise
reading, the field of view, the back-projection candidates) begun in a background thread while
the launcher loads nerfstudio.

A launcher spends seconds importing nerfstudio and parsing its command line (Python code, one
core, holding the interpreter's lock) before the model asks for its start.  The start needs only
the tilt series, and on the CPU its work is in large NumPy, SciPy and torch operations that
release that lock.  So :func:`begin` reads the tilt series a command line names (the reader's
defaults) and computes its start in a thread; the model asks :func:`take` with the
series, the normalisation and the options it has, and gets the thread's start only where every
input is the same; otherwise None, and it computes its own.  A run's result never depends on
whether the thread ran.  No nerfstudio import: the thread must not wait for the imports it
overlaps.

A thread and not a process: a process imports torch again beside the launcher and pays CUDA's
first-use costs that the run pays again.  Measured: Au noise 200, step 50's time after launch on
the 2-core CPU, 8.2-8.7 s against 9.1-10.4 s without it.
"""

from __future__ import annotations

import importlib
import os
import sys
import threading
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dataparsers.tilt_series_format import load_tilt_series
from gaussian_atoms_method.launch.handover import quick_handover
from gaussian_atoms_method.physics.devices import HOST, gpu
from gaussian_atoms_method.physics.units import Normalisation, normalised_projections


@dataclass
class _Ahead:
    """A start begun by :func:`begin`: its thread and, once done, its inputs and result."""

    data: Path
    extended_object: str
    max_atom_sigma_A: float | None
    """None: the option's default (read in the thread, which imports torch)."""
    thread: threading.Thread | None = None
    read: threading.Event = field(default_factory=threading.Event)
    """Set once the thread has read the series (or failed to)."""
    imported: threading.Event = field(default_factory=threading.Event)
    """Set once the thread has imported :data:`SHARED_IMPORTS` (or failed to)."""
    noise_known: threading.Event = field(default_factory=threading.Event)
    """Set once the thread has measured the noise (or will not)."""
    noise: object = None
    """The start's measured noise (:func:`measured_noise`), once ``noise_known``."""
    series: object = None
    projections: object = None
    """(V, H, W) tensor: the normalised projections."""
    normalisation: Normalisation | None = None
    start: object = None
    """The :class:`~gaussian_atoms_method.atoms.initialise.Start`, once computed."""


_ahead: _Ahead | None = None


def begin(
    data: Path, extended_object: str = "auto", max_atom_sigma_A: float | None = None, on_gpu: bool = True
) -> None:
    """Read the tilt series in ``data`` (a directory or manifest, the reader's defaults) and
    compute its back-projection start in a thread, for :func:`take`.  Errors are left to the
    run, which reads the series again and reports them in its own way.  Not a daemon: a process
    that exits while a daemon thread is inside a torch operation aborts ("terminate called
    without an active exception", seen on a GPU); a run stopped by its input ends at once
    through :func:`end_now`.

    The thread starts before the launcher has imported torch (this module does not import it):
    it imports scipy's shared packages (:data:`SHARED_IMPORTS`), reads the series and, where no
    GPU can be seen (:func:`gpu_possible`), their noise and the candidates' back-projection in
    numpy and scipy meanwhile, on a core the import leaves idle; then it imports torch (waiting
    for the launcher's import) for the rest.  With a GPU the two are made there first, as the
    run makes them, before the thread imports the candidates' modules: the device's work
    releases the interpreter's lock, so it runs while the launcher imports those modules itself
    (:func:`start_parts`, with the lock handed back quickly: :mod:`.launch.handover`)."""
    global _ahead
    ahead = _Ahead(Path(data), extended_object, None if max_atom_sigma_A is None else float(max_atom_sigma_A))

    def work() -> None:
        try:
            try:
                for name in SHARED_IMPORTS:
                    importlib.import_module(name)
            finally:
                ahead.imported.set()
            try:
                ahead.series = load_tilt_series(ahead.data)
            finally:
                ahead.read.set()
            series = ahead.series
            ahead.normalisation, scaled = normalised_projections(series)
            # with a GPU, host work beside the import would only slow it
            known = start_parts(ahead, scaled, HOST) if not (on_gpu and gpu_possible()) else None
            import torch

            device = gpu() if on_gpu else None  # torch is imported: ask it (a CPU run: the host's)
            if device is None and known is None:  # a GPU's files but no GPU torch can use: the host's
                known = start_parts(ahead, scaled, HOST)
            with quick_handover() if device is not None else nullcontext():
                if device is not None:
                    from gaussian_atoms_method.launch.kernel_warmup import begin as warm_kernels

                    warm_kernels("cuda", handover=True)  # beside the launcher's imports and this start
                    known = start_parts(ahead, scaled, str(device))
                ahead.noise = (known or {}).get("noise")
                ahead.noise_known.set()
                from gaussian_atoms_method.atoms.initialise import compute_start
                from gaussian_atoms_method.density.strategy import DensityControl

                if ahead.max_atom_sigma_A is None:
                    ahead.max_atom_sigma_A = DensityControl.max_atom_sigma_A
                ahead.projections = torch.from_numpy(scaled)
                ahead.start = compute_start(
                    ahead.series,
                    ahead.projections,
                    ahead.normalisation,
                    ahead.extended_object,
                    ahead.max_atom_sigma_A,
                    **(known or {}),
                    device=str(device) if device is not None else "cpu",
                )
        except Exception:  # noqa: BLE001 - the run computes its own start and reports the error there
            ahead.start = None
        finally:
            ahead.noise_known.set()

    ahead.thread = threading.Thread(target=work, name="gaussian-atoms start", daemon=False)
    _ahead = ahead
    ahead.thread.start()


SHARED_IMPORTS = (
    "scipy.linalg",
    "scipy.sparse",
    "scipy.sparse.csgraph",
    "scipy.spatial",
    "scipy.ndimage",
    "scipy.special",
    "scipy.fft",
)
"""scipy's packages that both the start's thread and the launcher import, imported by the thread
first, while the launcher imports torch (which imports none of them), and waited for by the
launcher before its own (:func:`settle_imports`).  scipy's packages import one another in
cycles (``scipy.linalg`` and its compiled ``cython_lapack``): two threads importing them at once
can each hold a module the other needs, and Python then stops one of them with
``_DeadlockError`` (seen once in a CPU run of ``gaussian-atoms train``, in the launcher).  Once
these are imported, what the two threads still import at once is this package's own modules,
which import no cycle (tests/test_layout.py)."""


def settle_imports() -> None:
    """Return once a start begun ahead has imported :data:`SHARED_IMPORTS` (at once where none
    was begun): a launcher calls it before importing the engine."""
    ahead = _ahead
    if ahead is not None:
        ahead.imported.wait()


def start_parts(ahead: _Ahead, scaled: np.ndarray, device) -> dict:
    """The start's noise reading and back-projection of ``ahead``'s series (``scaled``: its
    normalised projections) on ``device`` (:data:`HOST`: numpy and scipy, without torch), as
    :func:`~gaussian_atoms_method.atoms.initialise.compute_start` would make them there: its
    ``noise`` and ``backprojection`` arguments.  Needs only the physics modules."""
    from gaussian_atoms_method.physics.field_of_view import field_of_view
    from gaussian_atoms_method.physics.noise import measure_noise
    from gaussian_atoms_method.physics.reconstruction import backprojection_for_peaks

    series = ahead.series
    noise = measure_noise(scaled, device=device)
    slice_px = field_of_view(series, scaled, ahead.normalisation.length_scale, ahead.extended_object).slice_px
    volume = backprojection_for_peaks(
        series.projections,
        series.angles_deg,
        series.pixel_size_A,
        series.tilt_axis,
        series.centre_px,
        series.tilt_axis_angle_deg,
        slice_px,
        device,
    )
    return {"noise": noise, "backprojection": volume}


GPU_NODES = ("/dev/nvidiactl", "/dev/nvidia0", "/proc/driver/nvidia", "/dev/kfd")
"""Device files a GPU driver makes (NVIDIA's, and ROCm's ``/dev/kfd``): without any of them torch
can see no GPU, so the start runs on the CPU."""


def gpu_possible() -> bool:
    """Whether torch might see a GPU here (:data:`GPU_NODES`), asked without importing torch:
    where it cannot, the thread makes the CPU's noise reading and back-projection while the
    launcher imports torch (beside the import each slows the other: worth it only where they
    are the run's own)."""
    return any(os.path.exists(node) for node in GPU_NODES)


def measured_noise(series):
    """The noise the start begun ahead measured (:func:`start_parts`), once measured, where it
    was begun for the file ``series`` was read from; None otherwise.  Not handed out: the run
    reads the noise beside the candidates with it, and keeps that reading only where the start
    it takes (:func:`take`) holds this same noise."""
    ahead = _ahead
    if ahead is None or series is None or series.source is None:
        return None
    ahead.read.wait()
    if not _same_file(ahead, series):
        return None
    ahead.noise_known.wait()
    return ahead.noise


def _same_file(ahead: _Ahead, series) -> bool:
    return (
        ahead.series is not None
        and ahead.series.source is not None
        and series.source is not None
        and Path(series.source).resolve() == Path(ahead.series.source).resolve()
    )


def take(series, projections, normalisation: Normalisation, extended_object: str, max_atom_sigma_A: float):
    """The start :func:`begin` computed, if it was for these inputs (the tilt series' data and
    geometry, the normalised ``projections``, ``normalisation`` and the options); None
    otherwise, or when none was begun.  Waits for the thread when it read the same file; handed
    out once."""
    global _ahead
    ahead, _ahead = _ahead, None
    if ahead is None or series is None or projections is None:
        return None
    ahead.read.wait()
    if not _same_file(ahead, series):
        return None  # another file: not waited for
    ahead.thread.join()
    if ahead.start is None or not same_start_inputs(
        ahead, series, projections, normalisation, extended_object, max_atom_sigma_A
    ):
        return None
    return ahead.start


def prepared():
    """What this process's launcher prepared, for the fit it builds
    (:class:`~gaussian_atoms_method.engine.prepared.Prepared`): the start begun ahead
    (:func:`measured_noise`, :func:`take`) and the kernels' warm-up to wait for before a CUDA
    graph's capture (:func:`~gaussian_atoms_method.launch.kernel_warmup.wait`)."""
    from gaussian_atoms_method.engine.prepared import Prepared
    from gaussian_atoms_method.launch.kernel_warmup import wait

    return Prepared(noise=measured_noise, start=take, quiet=wait)


def end_now(status: int) -> None:
    """End the process with ``status`` at once where a start begun ahead is still being
    computed: a run stopped by its input (a bad option or file) before anything was written,
    which would otherwise wait for the thread (a thread cannot be stopped); the console is
    flushed first.  Returns where no start is running."""
    ahead = _ahead
    if ahead is not None and ahead.thread is not None and ahead.thread.is_alive():
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(status)


def same_start_inputs(
    ahead: _Ahead, series, projections, normalisation: Normalisation, extended_object: str, max_atom_sigma_A: float
) -> bool:
    """Whether ``ahead`` was computed from exactly these inputs: what :func:`compute_start` reads."""
    mine, theirs = ahead.series, series
    return (
        ahead.extended_object == extended_object
        and ahead.max_atom_sigma_A == float(max_atom_sigma_A)
        and ahead.normalisation == normalisation
        and mine.pixel_size_A == theirs.pixel_size_A
        and mine.tilt_axis == theirs.tilt_axis
        and mine.tilt_axis_angle_deg == theirs.tilt_axis_angle_deg
        and _same(mine.centre_px, theirs.centre_px)
        and _same(mine.angles_deg, theirs.angles_deg)
        and _same(mine.projections, theirs.projections)
        and ahead.projections.equal(projections.to(ahead.projections.device))
    )


def _same(a, b) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return np.array_equal(np.asarray(a), np.asarray(b))


TRAIN_OPTIONS = {
    "--data": "data",
    "--pipeline.model.extended-object": "extended_object",
    "--pipeline.model.max-atom-sigma-A": "max_atom_sigma_A",
}
"""The training options the start reads, with :func:`begin`'s argument for each."""
NOT_AHEAD = {
    "-h",
    "--help",
    "--load-config",
    "--load-dir",
    "--load-checkpoint",
    "--pipeline.model.init",
    "--pipeline.model.start-atoms",
}
"""Options after which no start is begun: help, a loaded run, a start other than the back-projection
(random, or given atoms)."""


def requested_start(argv: list[str]) -> dict | None:
    """:func:`begin`'s arguments for a training command line (``ns-train gaussian-atoms`` or
    ``gaussian-atoms train`` options: ``--data DIR``, before or after ``tilt-series``); None where
    it names no tilt-series directory, where the series would be read with options of its own
    (any after ``tilt-series`` but ``--data``), or where the start would not be the
    back-projection's (:data:`NOT_AHEAD`)."""
    cut = argv.index("tilt-series") if "tilt-series" in argv else len(argv)
    found: dict = {}
    for tokens, known, others_allowed in (
        (argv[:cut], TRAIN_OPTIONS, True),
        (argv[cut + 1 :], {"--data": "data"}, False),
    ):
        lowered = {name.lower(): key for name, key in known.items()}
        i = 0
        while i < len(tokens):
            name, has_value, value = _option(tokens[i])
            if name in {n.lower() for n in NOT_AHEAD}:
                return None
            if name in lowered:
                if not has_value:
                    if i + 1 >= len(tokens):
                        return None
                    value, i = tokens[i + 1], i + 1
                found[lowered[name]] = value
            elif name.startswith("-") and not others_allowed:
                return None  # the series read with options of its own
            i += 1
    if "data" not in found:
        return None
    try:
        return {
            "data": Path(found.pop("data")),
            **found,
            **({"max_atom_sigma_A": float(found["max_atom_sigma_A"])} if "max_atom_sigma_A" in found else {}),
        }
    except ValueError:
        return None


def _option(token: str) -> tuple[str, bool, str]:
    """A command-line token as (its name, whether it holds its value, that value), a long name
    in one spelling (``_`` as ``-``, lower case), as tyro reads it."""
    name, has_value, value = token.partition("=")
    return (name.replace("_", "-").lower() if name.startswith("--") else name), bool(has_value), value


DEVICE_OPTION = "--machine.device-type"


def runs_on_cuda(argv: list[str]) -> bool:
    """Whether a training command line (``gaussian-atoms train`` or ``ns-train gaussian-atoms``
    options) runs on CUDA, so that its launcher makes the GPU's context while torch imports
    (:mod:`.launch.cuda_context`): its :data:`DEVICE_OPTION` is ``cuda`` or not given (the
    default is CUDA where torch sees a GPU; where it sees none the driver finds none either);
    not for help."""
    for i, token in enumerate(argv):
        name, has_value, value = _option(token)
        if name in ("-h", "--help"):
            return False
        if name == DEVICE_OPTION:
            value = value if has_value else (argv[i + 1] if i + 1 < len(argv) else "")
            if value.lower() != "cuda":
                return False
    return True


def begin_for(argv: list[str]) -> bool:
    """:func:`begin` the start a training command line asks for (:func:`requested_start`), if
    any; returns whether one was begun."""
    request = requested_start(argv)
    if request is None:
        return False
    begin(**request, on_gpu=runs_on_cuda(argv))
    return True
