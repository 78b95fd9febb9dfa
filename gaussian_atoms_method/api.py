"""The Python API: a tilt series as arrays in, atoms out, through the same engine as the CLI::

    import gaussian_atoms_method as ga
    atoms = ga.reconstruct(projections, angles_deg, pixel_size_A=0.25)  # (N, H, W) views, (N,) angles
    atoms.positions, atoms.sigmas, atoms.position_std_A, atoms.atom_class

:func:`reconstruct` fits the arrays in memory with the engine ``gaussian-atoms train`` runs
(:mod:`gaussian_atoms_method.engine.run`: the same defaults; model options by their Python
names), with no nerfstudio import.  Bad input raises :class:`InputError`, whose message is the
line the CLI prints for the same input.
"""

from __future__ import annotations

import dataclasses
import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from dataparsers.errors import TiltSeriesError
from dataparsers.rosetta import stack_from_signal
from dataparsers.tilt_series_format import TiltSeries, load_tilt_series, write_tilt_series
from gaussian_atoms_method.atoms.atom_set import AtomFileError, AtomSet, read_atoms


class InputError(ValueError):
    """Input that cannot train; the message is the one line the CLI prints for it."""


def _input_error(exc: Exception) -> InputError:
    return InputError("gaussian-atoms: error: " + " ".join(str(exc).split()))


def read_tilt_series(path: str | Path, **options) -> TiltSeries:
    """Read a tilt series as ``ns-train gaussian-atoms`` does: a directory with
    ``tilt_series.json``, or a projection file with ``angles_deg=``/``pixel_size_A=`` where the
    file does not hold them (``options`` as :func:`dataparsers.tilt_series_format.load_tilt_series`).

    Returns
    -------
    TiltSeries
        ``projections`` (N, H, W) float32, ``angles_deg`` (N,), ``pixel_size_A``, and the geometry.
    """
    try:
        return load_tilt_series(Path(path), **options)
    except TiltSeriesError as exc:
        raise _input_error(exc) from None
    except TypeError as exc:  # an unknown or misspelt option
        raise _input_error(TiltSeriesError(f"read_tilt_series: {exc}")) from None


def _from_hyperspy(signal, angles_deg, pixel_size_A):
    """Projections, angles and pixel size from a HyperSpy signal (its axes' units and scales)."""
    title = getattr(getattr(signal.metadata, "General", None), "title", "") or "HyperSpy signal"
    axes = signal.axes_manager.as_dictionary()  # "axis-0", ...: the data's axes in array order
    as_dict = {
        "data": np.asarray(signal.data),
        "axes": [axes[f"axis-{k}"] for k in range(len(axes))],
        "metadata": signal.metadata.as_dictionary(),
    }
    stack = stack_from_signal(as_dict, Path(str(title)))
    if angles_deg is None and stack.angles_deg is None:
        raise TiltSeriesError(
            f"{title}: no tilt angles in the signal's axes or metadata.Tomography.tilts; pass angles_deg"
        )
    if pixel_size_A is None and stack.pixel_size_A is None:
        raise TiltSeriesError(f"{title}: the signal's axes have no length units; pass pixel_size_A")
    return (
        stack.projections,
        (stack.angles_deg if angles_deg is None else angles_deg),
        (stack.pixel_size_A if pixel_size_A is None else pixel_size_A),
    )


def _as_series(
    projections, angles_deg, pixel_size_A, tilt_axis: str, species=None, euler_convention=None, drop_views=None
) -> TiltSeries:
    from dataparsers.views import kept_views, views_of

    if isinstance(projections, TiltSeries):
        series, changes = projections, {"species": species, "euler_convention": euler_convention}
        kept = kept_views(drop_views, series.angles_deg)
        if kept is not None:
            series = views_of(series, kept)
        return dataclasses.replace(series, **{k: v for k, v in changes.items() if v is not None})
    source = "the pixel_size_A argument"
    if hasattr(projections, "axes_manager") and hasattr(projections, "metadata"):  # a HyperSpy signal
        source = source if pixel_size_A is not None else "the HyperSpy signal's axes"
        projections, angles_deg, pixel_size_A = _from_hyperspy(projections, angles_deg, pixel_size_A)
    if angles_deg is None:
        raise TiltSeriesError("angles_deg: the tilt angles are missing (one per projection, in degrees)")
    if pixel_size_A is None:
        raise TiltSeriesError("pixel_size_A: the pixel size is missing (Å)")
    try:
        pixel = float(pixel_size_A)
    except (TypeError, ValueError):
        raise TiltSeriesError(f"pixel_size_A must be a number of Å, got {pixel_size_A!r}") from None
    projections, angles = np.asarray(projections), np.asarray(angles_deg, dtype=np.float64)
    kept, given = kept_views(drop_views, angles), None
    if kept is not None:  # the views' indices are of the arrays given
        given = len(angles)
        projections, angles = projections[kept], angles[kept]
    return TiltSeries(
        projections,
        angles,
        pixel,
        tilt_axis,
        source=Path("projections"),
        species=species or (),
        euler_convention=euler_convention or "zyz",
        pixel_size_source=source,
        view_indices=kept,
        views_given=given,
    )


def _device(device: str) -> str:

    from gaussian_atoms_method.physics.devices import resolve

    try:  # "auto": the same default as ns-train gaussian-atoms without --machine.device-type
        return resolve(device)
    except ValueError as exc:
        raise TiltSeriesError(str(exc)) from None


def _whole(value, name: str) -> int:
    """``value`` as an int, or :class:`OptionError` naming the argument."""
    from gaussian_atoms_method.engine.errors import OptionError

    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise OptionError(f"{name} must be a whole number, got {value!r}")
    return int(value)


def _kept_series_dir(output_dir: Path) -> Path:
    """A new directory for a kept run's tilt series, ``OUTPUT/reconstruct/tilt_series/<time>_*``."""
    import time

    parent = output_dir / "reconstruct" / "tilt_series"
    parent.mkdir(parents=True, exist_ok=True)
    from gaussian_atoms_method.atoms.atom_set import current_umask

    made = Path(tempfile.mkdtemp(prefix=time.strftime("%Y-%m-%d_%H%M%S_"), dir=parent))
    made.chmod(0o777 & ~current_umask())  # mkdtemp makes it 0700; the directory follows the umask as mkdir would
    return made


def fit_options(model_options: dict[str, Any]):
    """The fit's options (:class:`~gaussian_atoms_method.engine.options.FitOptions`) with
    ``model_options`` set; an unknown name raises ``OptionError``."""
    from gaussian_atoms_method.engine.errors import OptionError
    from gaussian_atoms_method.engine.options import FitOptions

    options = FitOptions()
    names = {f.name for f in dataclasses.fields(options)}
    for name, value in model_options.items():
        if name not in names:
            raise OptionError(
                f"{name}: not a model option; the options are those of `ns-train gaussian-atoms --help` under "
                f"--pipeline.model, e.g. {sorted(names)[:4]}"
            )
        setattr(options, name, value)
    options.check()
    return options


def reconstruct(
    projections,
    angles_deg=None,
    pixel_size_A: float | None = None,
    *,
    device: str = "auto",
    tilt_axis: str = "y",
    species: str | None = None,
    euler_convention: str | None = None,
    drop_views=None,
    output_dir: str | Path | None = None,
    max_num_iterations: int | None = None,
    progress: bool = True,
    seed: int | None = None,
    **model_options,
) -> AtomSet:
    """Solve a tilt series for its atoms.

    Parameters
    ----------
    projections : (N, H, W) array, a HyperSpy ``Signal2D`` or a :class:`TiltSeries`
        Line integrals of the potential, one image per tilt.  A HyperSpy signal gives its pixel
        size (image axes in nm, Å or pm) and its angles (an angle-valued navigation axis, or
        ``metadata.Tomography.tilts``) unless they are passed.
    angles_deg : (N,) or (N, 3) array
        Tilt angles in degrees, about ``tilt_axis``; or Euler angles (phi, theta, psi), as
        GENFIRE and RESIRE refine them (:attr:`TiltSeries.euler_deg`).
    pixel_size_A : float
        Detector pixel size in Å.
    device : {"auto", "cpu", "cuda"}
        Where to train ("auto": the GPU when torch sees one).
    species : str, optional
        The specimen's elements, e.g. ``"Ta"`` or ``"Fe,Pt"``: they set the shortest distance two
        atoms may keep (:mod:`gaussian_atoms_method.atoms.hard_core`); without them it is read
        from the atoms found.
    euler_convention : {"zyz", "zyx"}, optional
        The axes of N x 3 Euler angles: Z-Y-Z as GENFIRE writes them (the default, or a
        :class:`TiltSeries`'s own), Z-Y-X as RESIRE does.
    drop_views : str or sequence, optional
        Views to leave out: their indices (``"3,7"``, ``[3, 7]``) or tilts (``"-40deg"``); a view
        that holds NaN or a blank frame is refused by its index and tilt until it is left out.
    output_dir : path, optional
        Keep the run here (``reconstruct/gaussian-atoms/<timestamp>``: ``config.yml`` for
        ``ns-viewer`` and ``gaussian-atoms view``, ``atoms.xyz``, ``classes.png``, ...) with the
        tilt series it was fitted to (``reconstruct/tilt_series/<time>_*``, which ``config.yml``
        names); by default both are written to a temporary directory and removed.
    max_num_iterations : int, optional
        As ``--max-num-iterations`` (default 3,000; training stops earlier once converged).
    seed : int, optional
        The fit's own generators' seed, as ``--pipeline.model.seed`` (its random draws: the
        duplications' directions, the views' order in the final refit; default that option's).
        The caller's generators are neither seeded nor drawn from.
    **model_options
        The ``--pipeline.model.*`` options by their Python names, e.g. ``psf="none"``,
        ``background="smooth"``, ``merge_threshold_A=0.7``.

    Returns
    -------
    AtomSet
        The atoms, in Å about the tilt centre (in a :class:`TiltSeries`'s truth frame when one is
        given, as the CLI writes them): ``positions`` (M, 3), ``sigmas``, ``amplitudes``,
        ``position_std_A`` (M, 3) and ``atom_class`` (1..k by mass); ``info["non_atoms"]``
        holds the Gaussians not reported as atoms, where the run learned a per-view registration
        ``info["view_shifts_px"]`` (V, 2) and ``info["view_gains"]`` (V,) as ``registration.csv``
        holds them, and with ``output_dir`` ``info["run_dir"]`` the run directory.

    Raises
    ------
    InputError
        For input that cannot train, with the one-line message the CLI prints.
    """
    from gaussian_atoms_method.engine.errors import OptionError
    from gaussian_atoms_method.engine.run import MAX_ITERATIONS, RunSettings, check_settings, fit_tilt_series
    from gaussian_atoms_method.engine.run_files import SEED, RunPlace

    keep = output_dir is not None
    work = None if keep else Path(tempfile.mkdtemp(prefix="gaussian-atoms-"))
    try:
        try:
            series = _as_series(projections, angles_deg, pixel_size_A, tilt_axis, species, euler_convention, drop_views)
            truth = read_atoms(series.truth_path) if series.truth_path is not None else None
            steps = MAX_ITERATIONS if max_num_iterations is None else _whole(max_num_iterations, "max_num_iterations")
            settings = RunSettings(
                RunPlace(Path(output_dir) if keep else work, "reconstruct"),
                _device(device),
                steps,
                steps,
                SEED,  # the machine seed config.yml records: the engine draws from none of the global generators
                progress,
                tensorboard=keep,  # a run not kept keeps no logs or checkpoints
                checkpoints=keep,
                kept=keep,
            )
            check_settings(settings)
            options = fit_options(model_options if seed is None else {**model_options, "seed": _whole(seed, "seed")})
        except (TiltSeriesError, AtomFileError, OptionError) as exc:
            raise _input_error(exc) from None
        # A kept run's config.yml names its data: they are written beside it, where ns-viewer and
        # gaussian-atoms view find them; the fit itself reads the arrays in memory.
        data = _keep_series(series, truth, Path(output_dir)) if keep else Path("in-memory")
        run = fit_tilt_series(series, options, settings, data)
        atoms = run.report.atoms  # from memory: the atoms the run wrote to atoms.xyz
        atoms.info["non_atoms"] = run.report.non_atoms
        if run.report.registration is not None:
            atoms.info["view_shifts_px"], atoms.info["view_gains"] = run.report.registration
        if keep:
            atoms.info["run_dir"] = run.run_dir
        return atoms
    finally:
        if work is not None:
            shutil.rmtree(work, ignore_errors=True)


def _keep_series(series: TiltSeries, truth, output_dir: Path) -> Path:
    """``series`` written as a tilt-series directory under ``output_dir`` (:func:`_kept_series_dir`)."""
    return write_tilt_series(
        _kept_series_dir(output_dir),
        series.projections,
        series.orientations_deg,
        series.pixel_size_A,
        truth,
        series.origin_A,
        series.tilt_axis,
        centre_px=series.centre_px,
        tilt_axis_angle_deg=series.tilt_axis_angle_deg,
        species=series.species,
        euler_convention=series.euler_convention,
    )
