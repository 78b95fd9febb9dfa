"""A replica of a user's own experiment: a tilt series with a known truth in the geometry of a
real one, to ask "what would my experiment recover?" before trusting its atoms.

From the real series (:class:`~dataparsers.tilt_series_format.TiltSeries`) the replica takes
every view's orientation (tilts or Euler angles in their convention), the detector's size, pixel
and tilt centre, and the noise read from the views themselves
(:func:`~gaussian_atoms_method.physics.noise.noise_from_projections`: a read variance and a
Poisson-like gain).  Onto that geometry it projects atoms the user gives (their model, or one the
harness builds) through physics the fit does not share (:mod:`.adf`), as everything a measured
view holds:

* each atom abTEM's Lobato projected potential of its element (a sharp core and long tails) with
  the integrated intensity ``Z^1.7`` of ADF-STEM's contrast, projected with the views' whole
  orientation (``potential="lobato"``, the default; ``"gaussian"`` draws each atom as an isotropic
  Gaussian of width ``atom_sigma_A`` instead, the fit's own model: a unit test, not evidence);
* an optional amorphous carbon support film (``support_A`` thick, at carbon's 0.1 atoms per Å³)
  of real carbon atoms under the atoms, through which every ray passes, wider than the field so
  high tilts see it too;
* the intensity of a probe from its optics (:class:`.microscope.ProbeOptics`: an aberrated core
  with rings and tails, an effective source, a halo), or a Gaussian one;
* the real views' mean level: one scale takes the replica's mean onto theirs;
* per-view misregistration (``shift_px`` RMS, random shifts of each view), per-view gain
  (``gain_scatter``, relative) and scan jitter (``scan_jitter_px``: each scan line its own shift);
* noise of the variance the real views were read to hold at each level, and, as measured views
  are cropped and aligned by interpolation, optionally made correlated by such a crop
  (``crop_order``, :func:`interpolated_crop`).

The truth is the atoms given (the support's carbon is not an atom to find); a measured model's
pairs closer than the shortest bond their elements can form, which no specimen holds, are set
aside first (:func:`physical_truth`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage

from gaussian_atoms_method.atoms.atom_set import AtomSet
from gaussian_atoms_method.physics.microscope import DEFAULT_OPTICS, ProbeOptics

CARBON_DENSITY_PER_A3 = 0.10
"""Amorphous carbon support films: 1.9-2.2 g/cm³, 0.095-0.11 carbon atoms per Å³."""


@dataclass
class Replica:
    """``projections`` (V, H, W) float32 in the real series' geometry; ``truth`` the atoms in its
    frame about the tilt centre; ``shifts_px`` (V, 2) the misregistration applied; ``gains``
    (V,); ``scale`` the intensity per unit of ``Z^1.7``-weighted mass; ``noise`` the real views'
    noise model it drew from; ``drawn_noise`` (V, H, W) float32 the noise in ``projections`` (what
    a run's noise reading is checked against)."""

    projections: np.ndarray
    truth: AtomSet
    shifts_px: np.ndarray
    gains: np.ndarray
    scale: float
    noise: object
    drawn_noise: np.ndarray | None = None


def _support_atoms(series, thickness_A: float, below_A: float, rng) -> np.ndarray:
    """Carbon positions of a slab ``thickness_A`` thick whose top is at depth ``below_A``, wide
    enough that every view's rays through the field cross it (the field plus the slab's depth
    times the steepest tilt's tangent)."""
    h, w = series.image_shape
    px = series.pixel_size_A
    steepest = np.deg2rad(min(np.max(np.abs(series.angles_deg)), 80.0))
    reach = (abs(below_A) + thickness_A) * np.tan(steepest)
    centre = np.asarray(series.centre_px)
    lo = np.array([-centre[0] * px - reach, -centre[1] * px - reach])
    hi = np.array([(h - 1 - centre[0]) * px + reach, (w - 1 - centre[1]) * px + reach])
    if series.tilt_axis == "x":  # the reach is across the tilt axis
        lo[0], hi[0] = -centre[0] * px, (h - 1 - centre[0]) * px
    else:
        lo[1], hi[1] = -centre[1] * px, (w - 1 - centre[1]) * px
    area = np.prod(hi - lo)
    n = rng.poisson(CARBON_DENSITY_PER_A3 * area * thickness_A)
    xy = rng.uniform(lo, hi, size=(n, 2))
    z = rng.uniform(below_A - thickness_A, below_A, size=n)
    return np.c_[xy, z]


def _project(positions, sigmas, masses, axes, series) -> np.ndarray:
    """(V, H, W) exact projections of Gaussians of integrated ``masses`` on the series' detector."""
    from gaussian_atoms_method.physics.geometry import pixel_centres
    from gaussian_atoms_method.physics.projector import project_gaussians

    h, w = series.image_shape
    rows = torch.from_numpy(pixel_centres(h, series.pixel_size_A, series.centre_px[0]))
    cols = torch.from_numpy(pixel_centres(w, series.pixel_size_A, series.centre_px[1]))
    amplitudes = masses / (2 * np.pi * sigmas**2) ** 1.5
    means, s, a = (torch.from_numpy(np.ascontiguousarray(v, dtype=np.float64)) for v in (positions, sigmas, amplitudes))
    axes = torch.from_numpy(axes)
    out = [project_gaussians(means, s, a, axes[v : v + 4], rows, cols) for v in range(0, len(axes), 4)]
    return torch.cat(out).numpy()


def physical_truth(atoms: AtomSet) -> tuple[AtomSet, float, float]:
    """The most of ``atoms`` with no two closer than the shortest bond their elements can form
    (:func:`~gaussian_atoms_method.atoms.hard_core.most_apart`), that bond (of all their elements
    together, :func:`~gaussian_atoms_method.atoms.hard_core.shortest_bond_from_species`) and the
    closest distance among the atoms given, Å (inf with fewer than two).

    A replica's truth must be a specimen that can exist.  A measured model may hold pairs no
    material has (the Ta film's model: pairs down to 1.53 Å, where tantalum's bonds are 2.5-3.0 Å
    and none can be under 2.11; 412 of its 8,284 atoms are set aside).  The report's hard core
    lies below that bond by the room a measured pair needs (1.87 Å for Ta): a true pair within
    that room is reported as one atom whenever its measured distance falls under the core (on the
    Ta replicas, pairs 1.88-1.94 Å apart were all their misses), so scored against it a replica
    would measure the model's error, not what the experiment recovers.
    """
    from gaussian_atoms_method.atoms.hard_core import most_apart, shortest_bond_from_species
    from gaussian_atoms_method.atoms.pair_distribution import nearest_neighbour_distances

    if atoms.species is None or len(atoms) < 2:
        return atoms, 0.0, float("inf")
    bond_A = shortest_bond_from_species(sorted(set(atoms.species)))
    closest_A = float(nearest_neighbour_distances(atoms.positions).min())
    return atoms.subset(most_apart(atoms.positions, bond_A)), bond_A, closest_A


def replica_of(
    series,
    atoms: AtomSet,
    atom_sigma_A: float = 0.4,
    support_A: float = 0.0,
    probe: str = "aberrated",
    blur_sigma_A: float = 0.5,
    shift_px: float = 0.0,
    gain_scatter: float = 0.0,
    seed: int = 0,
    shifts_px: np.ndarray | None = None,
    potential: str = "lobato",
    optics: ProbeOptics = DEFAULT_OPTICS,
    scan_jitter_px: float = 0.0,
    crop_order: int = 0,
    noise_over_atom: float = 1.0,
    noise_sigma_A: float = 0.0,
) -> Replica:
    """A tilt series of ``atoms`` (positions about the tilt centre, Å, with species) in the
    geometry and noise of the real ``series`` (module docstring).

    Parameters
    ----------
    series : TiltSeries
        The real series whose geometry, mean level and noise the replica takes.
    atoms : AtomSet
    atom_sigma_A : float
        Each atom's width before the probe, Å, with ``potential="gaussian"`` (thermal motion and
        the atom's own potential: about 0.3-0.5 Å for heavy atoms at room temperature).
    support_A : float
        Thickness of an amorphous carbon support film under the atoms, Å (0: none).
    probe : {"aberrated", "gaussian", "none"}
        The probe's intensity: from ``optics`` (rings, tails, source, halo), a Gaussian of
        ``blur_sigma_A``, or none (Gaussian atoms only: an ADF atom is sharper than a pixel).
    shift_px : float
        RMS of each view's random shift along each detector axis, pixels.
    gain_scatter : float
        Relative RMS of each view's random gain.
    seed : int
    shifts_px : (V, 2) array, optional
        Each view's shift (rows, columns; pixels) instead of random ones: a misregistration
        measured on the real views (what a fit with ``refine_alignment`` says of them).
    potential : {"lobato", "gaussian"}
        Each atom abTEM's Lobato projected potential (independent physics), or a Gaussian.
    optics : ProbeOptics
        The aberrated probe's optics (``probe="aberrated"``).
    scan_jitter_px : float
        RMS of each scan line's own shift along the fast axis, pixels (:func:`.adf.scan_jitter`).
    crop_order : int
        The views cropped as a registration crops them (:func:`interpolated_crop`): each noisy view
        moved by a random sub-pixel shift with splines of this order, its atoms drawn where the
        shift brings them back to (0: not cropped).  The noise comes out correlated, as the
        interpolated crops of measured views hold it; its variance at each level stays the one drawn.
    noise_over_atom : float
        The views' noise over an atom of width ``noise_sigma_A`` in units of what their neighbouring
        pixels show: the factor a run prints where it reads the noise from what neighbouring views do
        not share (denoised or filtered views).  Above 1 the noise is drawn correlated with both
        readings (:func:`~gaussian_atoms_method.physics.correlated_noise.correlated_noise`): its
        pixels' variance the one read from the real views' neighbouring pixels, this factor over an
        atom.  1: white at the level the real views were read to hold.
    noise_sigma_A : float
        The atoms' width that factor was read at, Å (the run prints it with the factor).
    """
    from gaussian_atoms_method.physics.adf import adf_projections, adf_weights, scan_jitter
    from gaussian_atoms_method.physics.microscope import convolve_views, misregistered, probe_transfer
    from gaussian_atoms_method.physics.noise import noise_from_projections

    if atoms.species is None or not len(atoms):
        raise ValueError("the replica needs atoms with species")
    if probe not in ("aberrated", "gaussian", "none"):
        raise ValueError(f"probe must be 'aberrated', 'gaussian' or 'none', got {probe!r}")
    if potential not in ("lobato", "gaussian"):
        raise ValueError(f"potential must be 'lobato' or 'gaussian', got {potential!r}")
    if noise_over_atom < 1.0 or (noise_over_atom > 1.0 and noise_sigma_A <= 0):
        raise ValueError(
            f"noise_over_atom must be at least 1 and, above 1, come with the atoms' width it was read at "
            f"(noise_sigma_A > 0 Å), got {noise_over_atom:g} and {noise_sigma_A:g} Å"
        )
    if potential == "lobato" and probe == "none":
        raise ValueError(
            "an ADF atom is sharper than a pixel: only a probe band-limits it (probe 'aberrated' or 'gaussian')"
        )
    rng = np.random.default_rng(seed)
    axes = series.detector_axes()
    positions, species = atoms.positions, np.asarray(atoms.species)
    if support_A > 0:
        carbon = _support_atoms(series, support_A, float(atoms.positions[:, 2].min()) - 1.0, rng)
        positions, species = np.r_[positions, carbon], np.r_[species, np.full(len(carbon), "C")]
    weight = adf_weights(species)
    if potential == "lobato":  # the probe drawn with the atoms: their images are sharper than a pixel
        clean = adf_projections(
            positions,
            species,
            weight,
            axes,
            series.image_shape,
            series.pixel_size_A,
            series.centre_px,
            probe=probe_transfer(probe, optics, blur_sigma_A),
        )
    else:
        clean = _project(positions, np.full(len(positions), atom_sigma_A), weight, axes, series)
        if probe == "aberrated":
            clean = convolve_views(clean, optics.intensity(series.pixel_size_A))
        elif probe == "gaussian":
            clean = ndimage.gaussian_filter(clean, (0, *(2 * [blur_sigma_A / series.pixel_size_A])), mode="constant")
    real = np.asarray(series.projections, dtype=np.float64)
    scale = float(real.mean() / clean.mean())
    clean *= scale
    shifts = rng.normal(0.0, shift_px, size=(len(clean), 2)) if shift_px > 0 else np.zeros((len(clean), 2))
    if shifts_px is not None:
        shifts = np.asarray(shifts_px, dtype=np.float64).reshape(len(clean), 2)
    gains = 1.0 + rng.normal(0.0, gain_scatter, size=len(clean)) if gain_scatter > 0 else np.ones(len(clean))
    misregistered(clean, shifts, gains)
    if scan_jitter_px > 0:
        clean = scan_jitter(clean, scan_jitter_px, rng)[0]
    noise = noise_from_projections(real)
    crop = rng.uniform(-0.5, 0.5, size=(len(clean), 2)) if crop_order else np.zeros((len(clean), 2))
    if crop_order:  # the atoms drawn where the crop's shift will bring them back to
        clean = interpolated_crop(clean, -crop, 3)
    if noise_over_atom > 1.0:  # correlated as the views' disagreement reads them, at their pixels' variance
        from gaussian_atoms_method.physics.correlated_noise import correlated_noise

        draw = correlated_noise(clean.shape, noise_over_atom, noise_sigma_A / series.pixel_size_A, rng)
        variance = np.clip(noise.pixel_variance(clean), 0.0, None)
    else:
        draw = rng.standard_normal(clean.shape)
        variance = np.clip(noise.variance(clean), 0.0, None)
    drawn = draw * np.sqrt(variance)
    noisy = clean + drawn
    if crop_order:  # the crop is linear: the noise in the cropped views is the cropped noise
        noisy, drawn = interpolated_crop(noisy, crop, crop_order), interpolated_crop(drawn, crop, crop_order)
    return Replica(noisy.astype(np.float32), atoms, shifts, gains, scale, noise, drawn.astype(np.float32))


def interpolated_crop(views: np.ndarray, shifts_px: np.ndarray, order: int) -> np.ndarray:
    """(V, H, W) ``views`` each moved by its (rows, columns) shift in ``shifts_px`` (V, 2) with
    splines of ``order`` (:func:`scipy.ndimage.shift`), as a crop about a sub-pixel centre or an
    alignment moves measured views: their noise comes out correlated, a pixel's variance lower
    than the noise at low frequencies (0.54 of it at order 3 and random shifts in half a pixel,
    ``tests/test_noise.py``)."""
    return np.stack([ndimage.shift(v, s, order=order, mode="nearest") for v, s in zip(views, shifts_px)])


def write_replica(series, atoms: AtomSet, out_dir, origin_A=(0.0, 0.0, 0.0), extra: dict | None = None, **settings):
    """:func:`replica_of` ``series`` for ``atoms`` (in the series' truth frame, its tilt centre at
    ``origin_A``; ``settings`` as :func:`replica_of` takes them) written as a tilt-series
    directory ``out_dir`` in the series' geometry, with the atoms as its truth; returns the
    directory and the :class:`Replica`.  The noise drawn into the views is written beside them
    (``noise.npy``), for the run to check the noise it reads against."""
    from dataparsers.tilt_series_format import write_tilt_series

    origin = np.asarray(origin_A, dtype=np.float64)
    made = replica_of(series, atoms.shifted(-origin), **settings)
    written = write_tilt_series(
        out_dir,
        made.projections,
        series.orientations_deg,
        series.pixel_size_A,
        truth=atoms,
        origin_A=origin,
        tilt_axis=series.tilt_axis,
        centre_px=series.centre_px,
        tilt_axis_angle_deg=series.tilt_axis_angle_deg,
        species=series.species,
        euler_convention=series.euler_convention,
        extra=extra,
        noise=made.drawn_noise,
    )
    return written, made
