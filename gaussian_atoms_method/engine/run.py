"""A tilt series in memory to a finished run directory, without nerfstudio: what
``gaussian-atoms train`` and :func:`gaussian_atoms_method.reconstruct` run.

:func:`fit_tilt_series` seeds the generators as ``ns-train`` does, builds the view set once
(:class:`~.view_set.ViewSet`: the normalised projections, the views' poses, the normalisation),
the fit (:class:`~.fit.AtomFit`) and its loop (:mod:`.training`), writes the run's
``config.yml`` first (:mod:`.run_files`) and trains; the results are written by the fit.
"""

from __future__ import annotations

import random
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from gaussian_atoms_method.engine.errors import OptionError
from gaussian_atoms_method.engine.fit import AtomFit
from gaussian_atoms_method.engine.lean_torch import lean_torch
from gaussian_atoms_method.engine.options import FitOptions
from gaussian_atoms_method.engine.progress import ProgressBar
from gaussian_atoms_method.engine.run_files import (
    RunPlace,
    RunRecord,
    Scalars,
    options_dict,
    write_config,
    write_transforms,
)
from gaussian_atoms_method.engine.training import FitLoop, LoopSettings, train
from gaussian_atoms_method.engine.view_set import ViewSet
from gaussian_atoms_method.engine.views import views_from_tilt_series
from gaussian_atoms_method.physics.units import normalised_projections

MAX_ITERATIONS = 3000
"""The step limit (training stops earlier once the atoms are settled)."""


@dataclass
class RunSettings:
    """A run's settings beside the fit's options: where (``place``), on which ``device``, how
    many steps, the machine ``seed`` (Python's, NumPy's and torch's generators, as ``ns-train``'s
    ``--machine.seed``), a progress bar, TensorBoard scalars."""

    place: RunPlace = field(default_factory=RunPlace)
    device: str = "cpu"
    max_num_iterations: int = MAX_ITERATIONS
    schedule_steps: int = MAX_ITERATIONS
    seed: int = 42
    progress: bool = True
    tensorboard: bool = True
    save_every: int = 1000
    """Steps between checkpoints (0: none but the last; see ``checkpoints``)."""
    log_every: int = 10
    """Steps between the loss's TensorBoard scalars (``--logging.steps-per-log``)."""
    checkpoints: bool = True
    """Write checkpoints (``nerfstudio_models/``; the viewer and ``export`` read them)."""
    kept: bool = True
    """Whether the run's directory outlives the call; a run that is not kept names no file."""


def check_settings(settings: RunSettings) -> None:
    """Raise :class:`~.errors.OptionError`, naming the option, for a device this machine's torch
    cannot use or a step limit below 1."""
    from gaussian_atoms_method.physics.devices import usable

    if not usable(settings.device):
        raise OptionError(
            f"--machine.device-type {settings.device}: torch sees no such device here; use --machine.device-type cpu "
            f"(the default where no GPU is seen)"
        )
    steps = settings.max_num_iterations
    if isinstance(steps, bool) or not (isinstance(steps, int) and steps >= 1):
        raise OptionError(f"--max-num-iterations must be a whole number of steps, at least 1, got {steps!r}")


def seed_everything(seed: int) -> None:
    """Python's, NumPy's and torch's global generators, as ``ns-train`` seeds them."""
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def view_set_of(series) -> tuple[ViewSet, object]:
    """The view set of a :class:`~dataparsers.tilt_series_format.TiltSeries` and its views
    (:class:`~.views.OrthographicViews`), as the tilt-series dataparser hands them to the fit."""
    norm, scaled = normalised_projections(series)
    views = views_from_tilt_series(series, norm)
    view_set = ViewSet(
        series,
        torch.from_numpy(scaled),
        views.camera_to_worlds.clone(),
        norm,
        series.pixel_size_A,
        series.truth_path,
    )
    return view_set, views


def fit_tilt_series(
    series, options: FitOptions, settings: RunSettings, data: Path, dataparser_options: dict | None = None
) -> Path:
    """Fit ``series`` with ``options`` and return the run directory (``settings.place``, its
    experiment named after ``data``, the series' directory or file, which ``config.yml``
    records with ``dataparser_options``).  Raises ``FloatingPointError`` naming the step and
    the cause where the loss stops being finite."""
    lean_torch()  # torch's compiler front end and symbolic shapes stay unimported
    place = settings.place.resolved(data)
    run_dir = place.run_dir
    run_dir.mkdir(parents=True, exist_ok=True)
    record = RunRecord(
        place,
        Path(data),
        dict(dataparser_options or {}),
        options_dict(options),
        settings.max_num_iterations,
        settings.schedule_steps,
        settings.seed,
        settings.device,
        "tensorboard",
    )
    write_config(run_dir, record)
    seed_everything(settings.seed)
    view_set, views = view_set_of(series)
    fit = AtomFit(options, view_set).to(settings.device)
    fit.kept = settings.kept
    loop = FitLoop(fit, views, view_set.projections, settings.schedule_steps)
    write_transforms(run_dir)
    bar = ProgressBar(settings.max_num_iterations) if settings.progress else None
    scalars = Scalars(run_dir, settings.log_every) if settings.tensorboard else None
    loop_settings = LoopSettings(
        settings.max_num_iterations, settings.schedule_steps, settings.save_every, settings.checkpoints
    )
    try:
        train(loop, run_dir, loop_settings, bar, scalars)
    finally:
        if bar is not None:
            bar.close()
        if scalars is not None:
            scalars.close()
    return run_dir
