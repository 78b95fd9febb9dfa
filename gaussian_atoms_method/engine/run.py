"""A tilt series in memory to a finished run directory, without nerfstudio: what
``gaussian-atoms train`` and :func:`gaussian_atoms_method.reconstruct` run.

:func:`fit_tilt_series` builds the view set once
(:class:`~.view_set.ViewSet`: the normalised projections, the views' poses, the normalisation),
the fit (:class:`~.fit.AtomFit`) and its loop (:mod:`.training`), writes the run's
``config.yml`` first (:mod:`.run_files`) and trains; the results are written by the fit.
"""

from __future__ import annotations

import dataclasses
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import torch

from gaussian_atoms_method.engine.errors import OptionError
from gaussian_atoms_method.engine.fit import AtomFit
from gaussian_atoms_method.engine.options import FitOptions
from gaussian_atoms_method.engine.prepared import NOTHING, Prepared
from gaussian_atoms_method.engine.progress import ProgressBar
from gaussian_atoms_method.engine.run_files import (
    SEED,
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
from gaussian_atoms_method.physics.devices import run_on
from gaussian_atoms_method.physics.units import normalised_projections

MAX_ITERATIONS = 3000
"""The step limit (training stops earlier once the atoms are settled)."""


@dataclass
class RunSettings:
    """A run's settings beside the fit's options: where (``place``), on which ``device``, how
    many steps, the machine ``seed`` (``ns-train``'s ``--machine.seed``, which seeds the global
    generators there; recorded in ``config.yml``: the engine draws only from its own generators,
    seeded by the fit's ``seed``, and leaves the caller's global ones alone), a progress bar,
    TensorBoard scalars."""

    place: RunPlace = field(default_factory=RunPlace)
    device: str = "cpu"
    max_num_iterations: int = MAX_ITERATIONS
    schedule_steps: int = MAX_ITERATIONS
    seed: int = SEED
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
    series,
    options: FitOptions,
    settings: RunSettings,
    data: Path,
    dataparser_options: dict | None = None,
    prepared: Prepared = NOTHING,
) -> FitRun:
    """Fit ``series`` with ``options``: the run directory (``settings.place``, its experiment
    named after ``data``, the series' directory or file, which ``config.yml`` records with
    ``dataparser_options``) and what the run reported there, in memory (``prepared``: what a
    launcher prepared for the fit, :mod:`.prepared`).  Raises ``FloatingPointError`` naming the step and
    the cause where the loss stops being finite."""
    with run_on(settings.device):
        return _fit_tilt_series(series, options, settings, data, dataparser_options, prepared)


def _fit_tilt_series(series, options, settings, data, dataparser_options, prepared) -> FitRun:
    """:func:`fit_tilt_series`, its helpers on the run's device."""
    if options.decide_registration:
        options = dataclasses.replace(
            options, decide_registration=False, **choose_registration(series, options, settings)
        )
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
    view_set, views = view_set_of(series)
    fit = AtomFit(options, view_set, prepared).to(settings.device)
    fit.kept = settings.kept
    fit.progress = settings.progress
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
    return FitRun(run_dir, getattr(fit, "report", None))


@dataclass(frozen=True)
class FitRun:
    """A finished :func:`fit_tilt_series`: its ``run_dir`` and its
    :class:`~gaussian_atoms_method.engine.results.Report` (the atoms, non-atoms and learned
    registration it wrote; None where it wrote none)."""

    run_dir: Path
    report: object = None


REGISTRATION = {
    "off": (False, False),
    "shifts": (True, False),
    "gains": (False, True),
    "shifts and gains": (True, True),
}
"""The per-view registrations :func:`choose_registration` judges: ``refine_alignment`` and
``refine_gain`` for each."""


def choose_registration(series, options: FitOptions, settings: RunSettings) -> dict:
    """Which per-view registration to learn, as the views a fit did not see say: the even views
    fitted four ways (:data:`REGISTRATION`: without, with shifts, with gains, with both;
    ``options`` otherwise, ``settings``' device, steps and seed), each fit's Gaussians (atoms and
    non-atoms, through its kernel) predicting the odd views, each held-out view after its own
    best shift and gain (:func:`~gaussian_atoms_method.atoms.view_prediction.held_out_rms`); the
    one that predicts them best.  Shifts and gains are judged apart because together they can
    trade: on the real Ta sub-area 25 shifts alone learn the pattern every sub-area of the film
    shares (correlation 1.00 with sub-area 23's), with gains beside them they wander to 4.6 px.
    Prints the four residuals and the choice; returns the options' values
    (``{"refine_alignment": bool, "refine_gain": bool}``)."""
    from dataparsers.views import views_of
    from gaussian_atoms_method.atoms.view_prediction import held_out_rms, run_gaussians, run_kernel
    from gaussian_atoms_method.engine.console import CONSOLE

    if series.n_views < 4:
        raise OptionError(
            f"--pipeline.model.decide-registration needs at least 4 views (two to fit, two to judge), got "
            f"{series.n_views}"
        )
    fitted, held = views_of(series, range(0, series.n_views, 2)), views_of(series, range(1, series.n_views, 2))
    fitted = dataclasses.replace(fitted, truth_path=None)  # scored by the views, not a truth
    rms = {}
    for name, (shifts, gains) in REGISTRATION.items():
        trial = dataclasses.replace(options, decide_registration=False, refine_alignment=shifts, refine_gain=gains)
        with tempfile.TemporaryDirectory(prefix="gaussian-atoms-registration-") as work, CONSOLE.capture():
            quiet = dataclasses.replace(
                settings, place=RunPlace(Path(work), "registration"), progress=False, tensorboard=False,
                checkpoints=False, kept=False,
            )  # fmt: skip
            run_dir = fit_tilt_series(fitted, trial, quiet, Path("in-memory")).run_dir
            rms[name] = held_out_rms(run_gaussians(run_dir), held, run_kernel(run_dir), fit_registration=True)
    best = min(rms, key=lambda name: (rms[name], list(REGISTRATION).index(name)))  # a tie: the fewer parameters
    CONSOLE.print(
        f"gaussian-atoms: per-view registration: {best} (a fit of the even views predicts the odd ones to "
        + ", ".join(f"{rms[name]:.4g} RMS with {name}" if name != "off" else f"{rms[name]:.4g} without" for name in rms)
        + "; input units, each held-out view after its own best shift and gain)"
    )
    return dict(zip(("refine_alignment", "refine_gain"), REGISTRATION[best]))
