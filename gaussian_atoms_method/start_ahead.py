"""The start of a run (:func:`~gaussian_atoms_method.atoms.initialise.compute_start`: the noise
reading, the field of view, the back-projection candidates) begun in a process of its own while
the launcher loads nerfstudio.

A launcher spends seconds importing nerfstudio and parsing its command line before the model
asks for its start, and the start needs only the tilt series.  So :func:`begin` starts a Python
process that reads the tilt series the command line names (the reader's defaults) and computes
its start; the model asks :func:`take` with the series, the normalisation and the options it has,
and gets that start only where every input is the same (:func:`inputs_digest`); otherwise None,
and it computes its own.  A run's result never depends on whether the process ran: the same
functions on the same inputs.  No nerfstudio import: the process would load it too.
"""

from __future__ import annotations

import atexit
import hashlib
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

from dataparsers.tilt_series_format import load_tilt_series
from gaussian_atoms_method.atoms.initialise import Start, compute_start
from gaussian_atoms_method.density.strategy import DensityControl
from gaussian_atoms_method.physics.units import Normalisation, normalised_projections

_ahead: subprocess.Popen | None = None


def begin(data: Path, extended_object: str = "auto", max_atom_sigma_A: float = DensityControl.max_atom_sigma_A) -> bool:
    """Start a Python process that reads the tilt series in ``data`` (a directory or manifest,
    the reader's defaults) and computes its start, for :func:`take`; returns whether one was
    begun.  A process of its own, not a thread: the launcher's imports hold the interpreter's
    lock, and a start of many small GPU operations in a thread waited for it at each one (Au
    noise 200 on the H100: no sooner); not forked: a fork after torch's thread pool has run
    hangs at the child's first parallel operation.  Its errors are left to the run, which reads
    the series again and reports them in its own way."""
    global _ahead
    stop()
    command = [sys.executable, "-m", __name__, str(data), extended_object, repr(float(max_atom_sigma_A))]
    try:
        _ahead = subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    except OSError:
        return False
    atexit.register(stop)
    return True


def take(series, projections, normalisation: Normalisation, extended_object: str, max_atom_sigma_A: float) -> Start | None:
    """The start :func:`begin` computed, if it was for these inputs (the tilt series' data and
    geometry, the normalised ``projections``, ``normalisation`` and the options: the same
    :func:`inputs_digest`); None otherwise, or when none was begun.  Waits for it only where it
    read the same file; handed out once."""
    global _ahead
    process, _ahead = _ahead, None
    if process is None:
        return None
    try:
        if series is None or projections is None or series.source is None or _receive(process) != str(Path(series.source).resolve()):
            return None  # another file: not waited for
        message = _receive(process)
    finally:
        _end(process)
    if message is None or message[0] != inputs_digest(series, projections, normalisation, extended_object, max_atom_sigma_A):
        return None
    return message[1]


def _send(out, message) -> None:
    data = pickle.dumps(message)  # plain pickle: the tensors' bytes
    out.write(len(data).to_bytes(8, "little") + data)
    out.flush()


def _receive(process: subprocess.Popen):
    try:
        size = int.from_bytes(process.stdout.read(8), "little")
        data = process.stdout.read(size)
        return pickle.loads(data) if size and len(data) == size else None
    except (OSError, EOFError, pickle.UnpicklingError):
        return None


def _end(process: subprocess.Popen) -> None:
    if process.poll() is None:
        process.kill()
    process.wait()
    process.stdout.close()


def stop() -> None:
    """End a start that was begun and not taken."""
    global _ahead
    process, _ahead = _ahead, None
    if process is not None:
        _end(process)


def inputs_digest(series, projections, normalisation: Normalisation, extended_object: str, max_atom_sigma_A: float) -> str:
    """A digest of everything :func:`~gaussian_atoms_method.atoms.initialise.compute_start` reads:
    the series' projections, angles and centre (bytes, type and shape), its pixel size, tilt
    axis and the axis' angle, the normalised ``projections``, ``normalisation`` and the options."""
    digest = hashlib.blake2b(digest_size=16)
    normalised = projections.detach().cpu().numpy() if hasattr(projections, "detach") else projections
    for array in (series.projections, normalised, series.angles_deg, series.centre_px):
        array = np.ascontiguousarray(array) if array is not None else np.zeros(0)
        digest.update(repr((array.dtype.str, array.shape)).encode())
        digest.update(memoryview(array).cast("B"))
    digest.update(repr((float(series.pixel_size_A), series.tilt_axis, float(series.tilt_axis_angle_deg), normalisation, extended_object, float(max_atom_sigma_A))).encode())
    return digest.hexdigest()


TRAIN_OPTIONS = {"--data": "data", "--pipeline.model.extended-object": "extended_object", "--pipeline.model.max-atom-sigma-A": "max_atom_sigma_A"}
"""The training options the start reads, with :func:`begin`'s argument for each."""
NOT_AHEAD = {"-h", "--help", "--load-config", "--load-dir", "--load-checkpoint", "--pipeline.model.init"}
"""Options after which no start is begun: help, a loaded run, a start other than the back-projection."""


def requested_start(argv: list[str]) -> dict | None:
    """:func:`begin`'s arguments for a training command line (``ns-train gaussian-atoms`` or
    ``gaussian-atoms train`` options: ``--data DIR``, before or after ``tilt-series``), or None
    where it names no tilt-series directory, or
    where the series would be read with options of its own (any after ``tilt-series`` but
    ``--data``) or the start would not be the back-projection's (:data:`NOT_AHEAD`)."""
    cut = argv.index("tilt-series") if "tilt-series" in argv else len(argv)
    found: dict = {}
    for tokens, known, others_allowed in ((argv[:cut], TRAIN_OPTIONS, True), (argv[cut + 1 :], {"--data": "data"}, False)):
        lowered = {name.lower(): key for name, key in known.items()}
        i = 0
        while i < len(tokens):
            name, has_value, value = tokens[i].partition("=")
            name = name.replace("_", "-").lower() if name.startswith("--") else name
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
        return {"data": Path(found.pop("data")), **found, **({"max_atom_sigma_A": float(found["max_atom_sigma_A"])} if "max_atom_sigma_A" in found else {})}
    except ValueError:
        return None


def begin_for(argv: list[str]) -> bool:
    """:func:`begin` the start a training command line asks for (:func:`requested_start`), if
    any; returns whether one was begun."""
    request = requested_start(argv)
    return begin(**request) if request is not None else False


def _compute(data: Path, extended_object: str, max_atom_sigma_A: float) -> None:
    """In the process :func:`begin` starts: write which file was read, then the start with the
    digest of its inputs (:func:`inputs_digest`), to stdout; None where anything failed."""
    out = sys.stdout.buffer
    try:
        series = load_tilt_series(data)
    except Exception:  # noqa: BLE001 - the run reads the series itself and reports the error
        return _send(out, None)
    _send(out, str(Path(series.source).resolve()) if series.source is not None else None)
    try:
        normalisation, scaled = normalised_projections(series)
        projections = torch.from_numpy(scaled)
        start = compute_start(series, projections, normalisation, extended_object, max_atom_sigma_A)
        message = (inputs_digest(series, projections, normalisation, extended_object, max_atom_sigma_A), start)
    except Exception:  # noqa: BLE001 - the run computes its own start
        message = None
    _send(out, message)


if __name__ == "__main__":
    _compute(Path(sys.argv[1]), sys.argv[2], float(sys.argv[3]))
