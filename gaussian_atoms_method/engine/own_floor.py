"""The error a run's stated precision cannot show, read by the run itself on a replica of its own atoms.

A run states each atom's precision from the scatter its views show.  A bias alike in every view
(an atom's sharp core and long tails and the probe's rings against the fit's Gaussians, a
misregistration spread over every atom) stays outside that statement: no fit sees it in its
own residual.  So, before the atoms are written, the run draws its own atoms again through
physics the fit does not share and asks how far its fit moves them:

* each reported atom (its element as the run names it, its fitted mass) is drawn as the power of
  Lobato's projected potential an ADF view holds (:mod:`~gaussian_atoms_method.physics.lobato`), through a
  probe read from the views, its aberration among :data:`PROBE_CANDIDATES` and its source
  (:func:`replica_probe`), in every view's geometry
  (:func:`~gaussian_atoms_method.physics.adf.adf_projections`, its deposit method); where the
  series says its views are phase images
  (:attr:`~dataparsers.tilt_series_format.TiltSeries.contrast`), as the projected potential
  itself through the aperture's double overlap (:mod:`~gaussian_atoms_method.physics.phase`): on
  7,000 carbon atoms in phase images at 2,000 e/Å² an ADF replica erred 14.2 / 12.7 / 15.9 pm
  against the fit's own 10.3 / 8.4 / 10.3, a phase replica 9.8 / 8.7 / 10.6 (both through the
  blur-shaped noise below);
* the rest of each view (the views' floors, the Gaussians not reported as atoms) as the fit
  renders it, with the atoms' amplitudes set to zero;
* each view moved and scaled by the registration the run learned, or else by what its views
  were read to sit off its atoms (:func:`registration_of`);
* noise of the variance the measured views hold at each level, as the run read it before its fit
  (:func:`~gaussian_atoms_method.physics.noise.noise_from_projections`); where it read the noise
  over an atom above a pixel's (from the views' spectrum beyond the atoms, or from what
  neighbouring views do not share: interpolated, filtered, denoised or band-limited views),
  correlated as that reading says (:func:`~gaussian_atoms_method.physics.correlated_noise.correlated_noise`:
  the pixels' variance the one read before the fit, the atoms' that many times it), not white at
  the atoms' level, which would put that level at every frequency the positions are read at (on
  carbon phase images, whose noise the aperture band-limits, the atoms read 13 times a pixel's
  variance, and the replica's refit erred 8.8 / 8.3 / 10.5 pm through white noise against
  7.5 / 7.1 / 8.9 correlated); for a phase series, with the spectrum the fit's residual shows
  (:func:`~gaussian_atoms_method.physics.correlated_noise.noise_shaped_like`: the aperture
  band-limits its noise as its signal).

Where the run holds more atoms than :data:`FLOOR_ATOMS`, the replica is a slab of them across
the tilt axis, drawn, refitted and read alone on the band of the detector it reaches
(:func:`floor_slab`); the floor is one error for every atom, and 2,000 read it as well as all.
The fit then starts at its own atoms, on the replica's views, with fresh moments, and refits them
as its final refit does (:func:`.refit.refit`, no density control) until its passes' means no
longer drift; the model is put back as it was afterwards.  Each atom's move, less the move common
to all (the scorers' global shift), is an error against a truth the run knows, and beside the
precision the run states for that atom it gives the floor
(:func:`~gaussian_atoms_method.atoms.calibration.precision_floor_A`) that the run adds in
quadrature to every atom's statement.

Why a warm refit, not a fit from the start: the floor is the error of the atoms found, and a
refit costs some passes over the views where a fit costs a run.  Why until no drift, over windows
that double: the atoms walk away from the truth slowly, along the beam most, by less per pass than
the passes scatter.  Stopped when neighbouring passes agreed (as the final refit stops), the refit
of a 2,000-atom Ni-Pd-Pt particle through ADF physics had walked 5.5 pm along z of the 7-8 pm it
walks in five times as many passes, and the stated intervals held 0.92 / 0.93 / 0.88 (x, y, z);
until no drift (9 passes, 7.6 s) 0.95 / 0.95 / 0.92, against 0.74 / 0.72 / 0.73 without a floor,
where a whole second fit (``gaussian-atoms internal-floor``) read a floor of 3.6 / 3.8 / 5.1 pm and
this one reads 4.1 / 4.2 / 4.3 pm.

The replica's probe is the candidate that best explains the views, not the microscope's own,
which nothing here knows: the floor holds the bias of that physics.
"""

from __future__ import annotations

import copy
import dataclasses
import time
from dataclasses import dataclass

import numpy as np
import torch

from gaussian_atoms_method.atoms.atom_set import AtomSet
from gaussian_atoms_method.engine.console import CONSOLE
from gaussian_atoms_method.physics.microscope import DEFAULT_OPTICS, ProbeOptics

MATCH_RADIUS_A = 0.75
"""The scoring radius of the method's paper: an atom the refit moves farther than this is not
found again, and its move is not a precision's error."""

MAX_PASSES = 40
"""The most passes the replica's refit takes (a budget, not a criterion: it stops once its
passes' means no longer drift; on the 2,000-atom Ni-Pd-Pt particle after 9)."""

DEAD_LOG_AMPLITUDE = -80.0
"""A log-amplitude whose Gaussian renders nothing (``exp(-80)`` ~ 2e-35 of a unit peak)."""


@dataclass
class OwnFloor:
    """``floor_A`` (3,) the error along x, y, z (Å) the stated precision did not hold on the run's
    own replica; ``coverage_95`` (3,) the share of its errors inside the run's stated 95%
    intervals (over the atoms its refit kept within :data:`MATCH_RADIUS_A`); ``rms_A`` (3,) their
    errors' RMS; ``steps`` the refit's steps; ``probe`` the replica's (:func:`replica_probe`);
    ``atoms`` how many it was read on (:func:`floor_slab`)."""

    floor_A: np.ndarray
    coverage_95: np.ndarray
    rms_A: np.ndarray
    steps: int
    probe: ProbeOptics = DEFAULT_OPTICS
    atoms: int = 0


def registration_of(info: dict, n_views: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The misregistration a replica of a run's atoms is given: each view's shift (V, 2)
    (pixels, rows and columns) and gain (V,).  The shifts and gains the run learned
    (``info["view_shifts_px"]``, ``info["view_gains"]``), else what its views were read to sit
    off its atoms (``info["view_offsets_px"]``, ``info["view_gain_offsets"]``), else random shifts
    of the RMS it read (``info["view_shifts_rms_px"]``), else none.

    >>> shifts, gains = registration_of({"view_shifts_rms_px": [0.5, 0.0]}, 400)
    >>> round(float(shifts[:, 0].std()), 1), float(abs(shifts[:, 1]).max()), float(gains.min())
    (0.5, 0.0, 1.0)
    """
    shifts = info.get("view_shifts_px", info.get("view_offsets_px"))
    if shifts is None:
        rms = np.asarray(info.get("view_shifts_rms_px", (0.0, 0.0)), dtype=np.float64)
        shifts = np.random.default_rng(seed).normal(0.0, 1.0, size=(n_views, 2)) * rms
    gains = info.get("view_gains", info.get("view_gain_offsets"))
    gains = np.ones(n_views) if gains is None else np.asarray(gains, dtype=np.float64)
    return np.asarray(shifts, dtype=np.float64).reshape(n_views, 2), gains.reshape(n_views)


FLOOR_ATOMS = 2000
"""The reported atoms a replica's floor is read on where a run holds more (:func:`floor_slab`):
the share of n errors inside their 95% intervals scatters by ``sqrt(0.05 * 0.95 / n)``, 0.5% at
2,000, a tenth of the 0.90-0.98 band the intervals are asked to hold."""


def tilt_axis(detector_axes: np.ndarray) -> tuple[int, np.ndarray] | None:
    """(k, (3,)): the detector axis every view shares (a single-axis series' tilt axis, unit
    length), the rows' (k 0) or the columns' (k 1); None where none is shared (two axes, learned
    tilts, views turned in their plane).

    >>> c, s = np.cos(0.3), np.sin(0.3)
    >>> tilt_axis(np.array([[[1.0, 0, 0], [0, 1, 0]], [[c, 0, s], [0, 1, 0]]]))
    (1, array([0., 1., 0.]))
    >>> tilt_axis(np.array([[[1.0, 0, 0], [0, 1, 0]], [[c, s, 0], [-s, c, 0]]])) is None
    True
    """
    axes = np.asarray(detector_axes, dtype=np.float64)[:, :2, :]
    for k in range(2):
        if np.allclose(axes[:, k], axes[0, k], rtol=0.0, atol=1e-9):
            return k, axes[0, k] / np.linalg.norm(axes[0, k])
    return None


def floor_slab(
    positions_A: np.ndarray, reported: np.ndarray, axis: np.ndarray | None, floor_atoms: int = FLOOR_ATOMS
) -> tuple[np.ndarray, np.ndarray]:
    """(G,) bool over the Gaussians at ``positions_A`` (G, 3): those the run's own replica draws
    and refits; (R,) bool over the ``reported`` (G,) ones: those its floor is read on.  With more
    than ``floor_atoms`` reported and a shared tilt ``axis`` (:func:`tilt_axis`): the slab across
    the axis, about the reported atoms' median, that holds ``floor_atoms`` of them, read on, and
    :data:`~gaussian_atoms_method.atoms.evidence.NEIGHBOUR_SEARCH_A` more either side, drawn and
    refitted with them; else every Gaussian.

    Why a slab across the tilt axis: an atom's place along that axis is the same row of every
    view, so the Gaussians beyond the slab never project onto those within it farther than their
    distance apart, and the slab is a tomographic problem of its own; the atoms read lie farther
    than the evidence's neighbour search from its faces, where the views couple two atoms'
    parameters by well under the evidence's floor.  The middle slab holds the thickest columns:
    its floor is the central atoms', not less than the average's.  On the 76,000-atom particle
    the replica had taken 14.8 of the run's 112 s on one H100.

    >>> rng = np.random.default_rng(0)
    >>> points = rng.uniform(-30.0, 30.0, (6000, 3))
    >>> keep, read = floor_slab(points, np.ones(6000, bool), np.array([0.0, 1.0, 0.0]))
    >>> int(read.sum()), bool(keep[read.nonzero()[0]].all()), round(float(keep.mean()), 2)
    (2000, True, 0.53)
    """
    reported = np.asarray(reported, bool)
    every = np.ones(len(positions_A), bool), np.ones(int(reported.sum()), bool)
    if axis is None or reported.sum() <= floor_atoms:
        return every
    from gaussian_atoms_method.atoms.evidence import NEIGHBOUR_SEARCH_A

    along = np.asarray(positions_A, dtype=np.float64) @ axis
    centre = np.median(along[reported])
    half = np.sort(np.abs(along[reported] - centre))[floor_atoms - 1]
    keep = np.abs(along - centre) <= half + NEIGHBOUR_SEARCH_A
    return (keep, np.abs(along[reported] - centre) <= half) if not keep.all() else every


STAND_IN_ELEMENT = "Pd"
"""The element an atom of no named element is drawn as (its fitted mass kept): through a probe the
shape of an atom's image hardly depends on its element, and the source read from the views takes
up what does (ADF through a 0.7 Å source: carbon's least-squares width 0.663 Å, Pd's 0.637,
``docs/studies/atom_profile_gain.md``).  On the Au noise-200 particle without its elements the
replica of Pd atoms read a floor of 2.7 / 2.4 / 4.3 pm and the intervals held 0.945 / 0.950 /
0.940; with ``--species Au`` 2.7 / 2.5 / 4.2 pm and 0.945 / 0.953 / 0.933.  Pd lies mid-way
between the light and heavy atoms of the particles the harness draws."""


def drawable_species(species, n: int) -> tuple[np.ndarray, str]:
    """(N,) the element each of ``n`` atoms is drawn as in the run's own replica, and words for
    what was not named: Lobato's potentials come from their parameters
    (:mod:`~gaussian_atoms_method.physics.lobato`), so no simulator need be installed.  An atom of
    no element (``species`` None, or ``"X"``: not named, or of a class no element's) is drawn as
    the run's most common element, or as :data:`STAND_IN_ELEMENT` where none is named.

    >>> drawable_species(np.array(["Ta", "X", "Ta"]), 3)
    (array(['Ta', 'Ta', 'Ta'], dtype='<U2'), '1 atom of no element drawn as Ta')
    >>> drawable_species(None, 2)[1]
    'drawn as Pd, no element given'
    """
    unnamed = np.ones(n, bool) if species is None else np.asarray(species) == "X"
    if unnamed.all():
        return np.full(n, STAND_IN_ELEMENT), f"drawn as {STAND_IN_ELEMENT}, no element given"
    if not unnamed.any():
        return np.asarray(species), ""
    named, counts = np.unique(np.asarray(species)[~unnamed], return_counts=True)
    common, k = str(named[np.argmax(counts)]), int(unnamed.sum())
    return np.where(unnamed, common, species), f"{k} atom{'s' if k != 1 else ''} of no element drawn as {common}"


def drawn_atoms(series, atoms: AtomSet, optics, views=slice(None), window=None) -> np.ndarray:
    """(V, H, W) ``atoms`` (Å, the truth frame, with ``species`` and masses) drawn in the
    ``views`` of ``series`` through ``optics`` as its contrast images them
    (:func:`~gaussian_atoms_method.physics.probe_width.contrast_transfer`), input units; ``optics``
    None: ADF's contrast through no probe, band-limited at the detector's Nyquist frequency;
    ``window`` (k, cut): the detector's rows (k 0) or columns (k 1) ``cut`` alone."""
    from gaussian_atoms_method.physics.adf import ADF_POTENTIAL_POWER, adf_projections
    from gaussian_atoms_method.physics.microscope import band_limit
    from gaussian_atoms_method.physics.probe_width import contrast_transfer

    if optics is None:
        transfer, power = band_limit(series.pixel_size_A), ADF_POTENTIAL_POWER
    else:
        transfer, power = contrast_transfer(optics, series.contrast)
    about_centre = atoms.positions - np.asarray(series.origin_A, dtype=np.float64)
    shape, centre = list(series.image_shape), np.array(series.centre_px, dtype=np.float64)
    if window is not None:  # the same pixels, counted from the window's first
        k, cut = window
        shape[k], centre[k] = cut.stop - cut.start, centre[k] - cut.start
    return adf_projections(
        about_centre, atoms.species, atoms.masses, series.detector_axes()[views], tuple(shape),
        series.pixel_size_A, tuple(centre), probe=transfer, method="deposit", power=power,
    )  # fmt: skip


PROBE_CANDIDATES = (ProbeOptics(defocus_A=0.0, cs_A=0.0),) + tuple(
    dataclasses.replace(DEFAULT_OPTICS, defocus_A=float(d)) for d in range(-100, 101, 20)
)
"""The probes an ADF replica's is read among (:func:`replica_probe`; sources read for each): an
aberration-free one (a corrected microscope's) and :data:`~gaussian_atoms_method.physics.microscope.DEFAULT_OPTICS`'s
(300 kV, 20 mrad, Cs 10 µm) at defoci from -100 to 100 Å, two depths of field (``lambda / alpha^2``,
49 Å) either side of focus, through the defocus that balances its Cs (about -54 Å).  Drawn
with :data:`DEFAULT_OPTICS`' rings whatever the views showed, the replica of the Au noise-200
particle (drawn with a Gaussian probe) read a floor that widened the run's 95% intervals to hold
0.98-0.99 of its errors."""

SOURCE_VIEWS = 12
"""The most views the source is read on (evenly spread over the series): each holds thousands of
frequencies in every ring of the cross-spectrum, and the reading costs a drawing of them."""


def replica_probe(model, atoms: AtomSet, registration):
    """The replica's probe read from the views: for ADF views the one of :data:`PROBE_CANDIDATES`
    that with its source best explains them
    (:func:`~gaussian_atoms_method.physics.probe_width.probe_read_from_views`, the reported atoms
    drawn through no probe); for phase images the aperture's transfer with the source read
    (:func:`~gaussian_atoms_method.physics.probe_width.source_read_from_views`, the atoms drawn
    with no source); each view moved and scaled by ``registration`` (shifts (V, 2) px, gains
    (V,)).  On the Au noise-200 particle (Lobato's potentials through a Gaussian probe of 0.5 Å,
    1.18 Å FWHM) it read no aberration and a 1.21 Å source, and the run's intervals held
    0.945 / 0.953 / 0.933 of its errors with the floor read (0.98-0.99 through
    :data:`~gaussian_atoms_method.physics.microscope.DEFAULT_OPTICS`' rings).  On 7,000 carbon atoms in phase images
    (drawn with a 0.7 Å source) it read 0.65 Å, and the replica erred 9.8 / 8.7 / 10.6 pm against
    the fit's own 10.3 / 8.4 / 10.3; the source that makes an isolated atom as wide as the fit
    renders its atoms (:func:`~gaussian_atoms_method.physics.probe_width.probe_as_wide_as`) read
    0.90 Å there (bonded atoms' fitted widths hold their neighbours' tails), and its replica erred
    13.7 / 12.2 / 15.2 pm.  On 2,000 Ni-Pd-Pt atoms through ADF (Cs 10 µm at 40 Å defocus, a 0.7 Å
    source) it read -60 Å and 1.00 Å (20 Å and 1.07 Å against the true atoms, a transfer within
    0.033 of the truth's: behind a source of about 1 Å these probes are one).  Where the views hold
    no correlation with the atoms: the source that makes an isolated atom as wide as the fit's."""
    from gaussian_atoms_method.physics.microscope import misregistered
    from gaussian_atoms_method.physics.probe_width import (
        probe_as_wide_as,
        probe_read_from_views,
        rendered_atom_width_A,
        source_read_from_views,
    )
    from gaussian_atoms_method.physics.psf import KERNEL_WIDTHS_A

    series = model.view_set.series
    views = np.unique(np.linspace(0, len(series.projections) - 1, SOURCE_VIEWS).round().astype(int))
    measured = np.asarray(series.projections, dtype=np.float64)[views]
    # ADF: no probe, its aberrations read with its source; a phase image's transfer is its
    # aperture's whatever the aberrations, drawn with no source, its source alone read
    bare = None if series.contrast == "adf" else dataclasses.replace(DEFAULT_OPTICS, source_fwhm_A=0.0)
    drawn = misregistered(drawn_atoms(series, atoms, bare, views), registration[0][views], registration[1][views])
    if bare is None:
        optics = probe_read_from_views(measured, drawn, series.pixel_size_A, PROBE_CANDIDATES)
    else:
        optics = dataclasses.replace(bare, source_fwhm_A=source_read_from_views(measured, drawn, series.pixel_size_A))
    if np.isfinite(optics.source_fwhm_A):
        return optics
    elements, counts = np.unique(np.asarray(atoms.species), return_counts=True)
    common = elements[np.argmax(counts)]
    sigma_A = float(np.median(atoms.sigmas[np.asarray(atoms.species) == common]))
    weights = tuple(model.view_params["psf"].detach().double().cpu().tolist()) if "psf" in model.view_params else ()
    width = rendered_atom_width_A(sigma_A, KERNEL_WIDTHS_A, weights)
    return probe_as_wide_as(str(common), width, DEFAULT_OPTICS, series.contrast)


def draw_replica(
    model, atoms: AtomSet, reported: np.ndarray, registration, seed: int, probe, residuals, window=None
) -> torch.Tensor:
    """(V, H, W) the replica's views (module text), normalised as the model's, on its device:
    ``atoms`` the reported atoms (Å, the truth frame, with ``species``), ``reported`` (N,) bool
    over the model's Gaussians, ``registration`` (shifts (V, 2) px, gains (V,)), ``residuals``
    (V, H, W) the fit's on its training views (normalised units; a phase series' noise takes
    their spectrum); ``window`` (k, cut): the detector's rows (k 0) or columns (k 1) ``cut``
    alone."""
    from gaussian_atoms_method.engine.refit import in_window
    from gaussian_atoms_method.engine.residuals import render_training_views
    from gaussian_atoms_method.physics.microscope import misregistered
    from gaussian_atoms_method.physics.noise import noise_from_projections

    series, scale = model.view_set.series, model.normalisation.data_scale
    log_amplitudes = model.gauss_params["log_amplitudes"]
    kept = log_amplitudes.detach().clone()
    mask = torch.as_tensor(reported, device=kept.device)
    try:
        with torch.no_grad():
            log_amplitudes.data[mask] = DEAD_LOG_AMPLITUDE
        rest = render_training_views(model).astype(np.float64)  # the floors and the non-atoms
    finally:
        with torch.no_grad():
            log_amplitudes.data.copy_(kept)
    drawn = misregistered(drawn_atoms(series, atoms, probe, window=window), *registration)
    clean = in_window(rest, window) + drawn * scale  # normalised units
    noise = getattr(model, "measured_noise", None)  # read from the views before the fit (normalised)
    if noise is None:
        noise = noise_from_projections(np.asarray(series.projections, dtype=np.float64) * scale)
    rng = np.random.default_rng(seed)
    if series.contrast == "phase":  # band-limited as the signal is: the shape the fit's residual shows
        from gaussian_atoms_method.physics.correlated_noise import noise_shaped_like

        shaped = in_window(noise_shaped_like(torch.as_tensor(residuals).double().cpu().numpy(), rng), window)
        draw, variance = shaped, np.clip(noise.pixel_variance(clean), 0.0, None)
    elif noise.correlation > 1.0:  # as the spectrum or the views' disagreement read it
        from gaussian_atoms_method.physics.correlated_noise import correlated_noise

        sigma_px = float(model.sigmas.detach().median()) / model.density.pixel_size  # the width it was read at
        draw = correlated_noise(clean.shape, noise.correlation, sigma_px, rng)
        variance = np.clip(noise.pixel_variance(clean), 0.0, None)
    else:
        draw, variance = rng.standard_normal(clean.shape), np.clip(noise.variance(clean), 0.0, None)
    noisy = clean + draw * np.sqrt(variance)
    return torch.as_tensor(noisy.astype(np.float32), device=model.means.device)


def read_own_floor(
    model,
    atoms: AtomSet,
    reported: np.ndarray,
    info: dict,
    residuals,
    noise: float,
    seed: int = 0,
    floor_atoms: int | None = None,
) -> OwnFloor:
    """The floor of the run's reported ``atoms`` (with their elements and stated
    ``position_std_A``), ``reported`` (N,) bool marking them among the model's Gaussians, read
    on the run's own replica (module text) of a slab of them (:func:`floor_slab`,
    ``floor_atoms``, default :data:`FLOOR_ATOMS`), its views registered as ``info`` says (:func:`registration_of`),
    ``residuals`` the fit's (:func:`draw_replica`) and ``noise`` their pixel noise (input units,
    :func:`~.results.residual_noise`), the one the refit judges in.
    The model is left as it was."""
    from gaussian_atoms_method.atoms.calibration import Z95, precision_floor_A
    from gaussian_atoms_method.engine.refit import refit, window_of
    from gaussian_atoms_method.engine.rendering import detector_axes

    n_views = len(model.view_set.series.projections)
    params = {name: p.detach().clone() for name, p in model.gauss_params.items()}
    registration = registration_of(info, n_views, seed)
    probe = replica_probe(model, atoms, registration)
    shared = tilt_axis(detector_axes(model.view_c2w.cpu().double()).numpy())
    keep, read = floor_slab(
        model.atoms().positions, reported, None if shared is None else shared[1], floor_atoms or FLOOR_ATOMS
    )
    in_slab = keep[np.asarray(reported, bool)]  # over the reported atoms
    atoms, reported, read = atoms.subset(in_slab), np.asarray(reported, bool)[keep], read[in_slab]
    states = {name: copy.deepcopy(o.state_dict()) for name, o in model.optimizers.items()}
    generator = model.generator.get_state()
    for o in model.optimizers.values():
        o.state.clear()  # fresh moments: training's early gradients would shrink every step
    try:
        with torch.no_grad():
            for p in model.gauss_params.values():  # the slab alone: a tomographic problem of its own
                p.data = p.data[torch.as_tensor(keep, device=p.device)]
        window = None if shared is None or keep.all() else window_of(model, _rows_of(model, *shared))
        replica = draw_replica(model, atoms, reported, registration, seed, probe, residuals, window)
        steps = refit(  # its bar in a terminal only: in a log, the line after it says what it took
            model,
            max_passes=MAX_PASSES,
            measured=replica,
            until_still=True,
            progress=model.progress,
            what="gaussian-atoms: own replica",
            in_logs=False,
            noise=noise,
            window=window,
        )
        moved = (model.atoms().positions[reported] - atoms.positions)[read]
    finally:
        with torch.no_grad():
            for name, p in model.gauss_params.items():
                p.data = params[name]
        for name, o in model.optimizers.items():
            o.load_state_dict(states[name])
        model.generator.set_state(generator)
    found = np.linalg.norm(moved - np.median(moved, axis=0), axis=1) <= MATCH_RADIUS_A
    error = moved[found] - np.median(moved[found], axis=0)
    stated = atoms.position_std_A[read][found]
    return OwnFloor(
        floor_A=precision_floor_A(error, stated),
        coverage_95=(np.abs(error) <= Z95 * stated).mean(axis=0) if found.any() else np.full(3, np.nan),
        rms_A=np.sqrt((error**2).mean(axis=0)) if found.any() else np.full(3, np.nan),
        steps=steps,
        probe=probe,
        atoms=int(read.sum()),
    )


SLAB_REACH_WIDTHS = 4.0
"""A Gaussian's image reaches this many of its widths across the slab's rows (3e-4 of its peak
beyond): the rows the replica of a slab is fitted on (:func:`_rows_of`)."""


def _rows_of(model, k: int, axis: np.ndarray) -> tuple[int, float, float]:
    """(k, lo, hi): the detector coordinates (normalised) along its axis ``k``, ``axis`` in
    the world, that the model's Gaussians reach (:data:`SLAB_REACH_WIDTHS`): beyond them a
    slab's views hold its floors and noise alone (:func:`.refit.window_of`)."""
    along = model.means.detach() @ torch.as_tensor(axis, dtype=model.means.dtype, device=model.means.device)
    reach = SLAB_REACH_WIDTHS * model.sigmas.detach().reshape(len(along), -1).max(dim=1).values
    return k, float((along - reach).min()), float((along + reach).max())


def widen_by_own_floor(
    model, atoms: AtomSet, reported: np.ndarray, hard_core_A: float, residuals, noise: float, registration=None
) -> None:
    """Read the run's own floor (:func:`read_own_floor`) and widen each of ``atoms``'
    statements by it (``position_std_A``, ``depth_halfwidth_A``, ``depth_open``;
    :func:`~gaussian_atoms_method.atoms.calibration.with_floor`), recorded in
    ``atoms.info["precision_floor_A"]`` (the atoms it was read on in ``"precision_floor_atoms"``);
    says what it read, or why it read nothing.  ``residuals``
    (V, H, W): the fit's on its training views, as the evidence read them, and ``noise`` their
    pixel noise (input units); ``registration``
    (shifts (V, 2) px, gains (V,)): what the run learned, if it did."""
    from gaussian_atoms_method.atoms.calibration import with_floor

    if not model.optimizers:
        CONSOLE.print("gaussian-atoms: no precision floor read on the run's own replica (no optimisers to refit with)")
        return
    info = dict(atoms.info)
    if registration is not None:
        info["view_shifts_px"], info["view_gains"] = registration
    started = time.perf_counter()
    drawn = copy.copy(atoms)
    drawn.species, unnamed = drawable_species(atoms.species, len(atoms))
    floor = read_own_floor(model, drawn, reported, info, residuals, noise, seed=model.config.seed)
    hard_core = hard_core_A if np.isfinite(hard_core_A) else None
    atoms.position_std_A, atoms.depth_halfwidth_A, atoms.depth_open = with_floor(
        atoms.position_std_A, atoms.depth_halfwidth_A, atoms.depth_open, floor.floor_A, hard_core, atoms.depth_rise
    )
    atoms.info["precision_floor_A"], atoms.info["precision_floor_atoms"] = floor.floor_A.tolist(), floor.atoms
    probe, seconds = floor.probe, time.perf_counter() - started
    slab = f"read on a slab of {floor.atoms:,} atoms across the tilt axis; " if floor.atoms < len(atoms) else ""
    median = np.nanmedian(atoms.position_std_A, axis=0)
    physics = (
        "phase images"
        if model.view_set.series.contrast == "phase"
        else "ADF, no aberration"
        if probe.cs_A == 0 and probe.defocus_A == 0
        else f"ADF, Cs {probe.cs_A / 1e4:g} µm at {probe.defocus_A:g} Å"
    )
    CONSOLE.print(
        f"gaussian-atoms: own replica ({physics}, {probe.source_fwhm_A:.2f} Å source read"
        f"{'; ' + unnamed if unnamed else ''}; {slab}{floor.steps} steps, {seconds:.1f} s): 95% intervals held "
        f"{'/'.join(f'{c:.2f}' for c in floor.coverage_95)}; floor {'/'.join(f'{f * 100:.1f}' for f in floor.floor_A)} "
        f"pm added: median precision {'/'.join(f'{v * 100:.1f}' for v in median)} pm"
    )
