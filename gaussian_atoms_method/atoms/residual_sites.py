"""Where the data hold mass that no Gaussian explains: atoms the start or the fit missed.

The residual projections (measured minus predicted) of a fit that has found every atom are
noise; an atom it missed leaves its projection in every view, and a filtered back-projection
of the residuals gathers those into a peak at the atom.  So, like the start
(:mod:`.candidates`), but on the residuals:

1. FBP with a Hann filter, smoothed by a Gaussian of ``smoothing_A`` (0.5 Å, about a blurred
   atom's width: a matched filter);
2. the noise of that volume read from the volume itself (1.4826 x its median absolute
   deviation: the residual volume is noise but for a few peaks);
3. local maxima above the level no noise peak reaches anywhere in the volume but with chance
   ``false_alarm_rate``: the expected Euler characteristic of a smooth Gaussian random field
   (:func:`random_field_threshold`; a smoothed back-projection of noise is one, its smoothness
   read from the volume's own gradients).  A Bonferroni bound over 1 Å^3 cells is too low
   for a smooth field: on the residual noise of a 6 Å Au sphere it gave 4.23 sigma and the
   noise's highest peak reached 4.38; the random-field level is 4.6.
4. the back-projection of one atom is not one peak: a limited tilt range and the filter give it
   side lobes that read as sites of their own (six beside one missing Au atom at a
   peak-to-noise of 40).  So the sites are taken strongest first, CLEAN-style: each accepted
   site's response (:func:`~.point_response.point_response`, the smoothed FBP of an atom at the tilt centre,
   shifted) is taken off the values of the sites not yet visited, which must still clear the
   level.  Then, at least ``min_distance_A`` apart and from every existing Gaussian
   (1 Å: closer than the shortest bond of any material, C-C 1.42 Å, so a missing neighbour
   of a fitted atom is not shadowed by it).
5. given the hard core, the places an atom could be (inside the material, at least the hard
   core from every Gaussian: :mod:`.holes`) are searched at a level of their own: a light atom
   whose neighbours took up part of its mass leaves a weaker peak, but only there.  That level
   is the Benjamini-Hochberg one over the peaks there (:func:`~.peaks.discovery_level`: no more
   noise peaks expected above it than ``false_alarm_rate`` of the peaks above it), never above
   the family-wise level for their own volume: where many atoms are missing, a few noise sites
   among them cost a refit, and the final prune judges every site.  Outside those places the
   whole volume's family-wise level holds: there the limited tilt range's streaks of strong
   missing atoms read as peaks (seven on an 11 Å Au sphere missing 40 atoms, at the discovery
   level, none at the family-wise one).  With the wait for weak additions still gaining mass
   (:meth:`..density.strategy.DensityControl.additions_settled`), on a 16,000-atom Ni-Pd-Pt
   particle through ADF physics the found atoms rose from 0.988 (Ni 0.963) to 0.999 (Ni 0.996)
   at the same 0.0076 false atoms per atom.

Each site's mass follows from its smoothed value ``v``: a Gaussian atom of width ``sigma``
reconstructed and smoothed by ``s`` peaks at ``M / (2 pi (sigma^2 + s^2))^(3/2)``.  A
limited tilt range lowers the peak, so the mass is a start the fit corrects.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from gaussian_atoms_method.atoms import maxima, volume_filters
from gaussian_atoms_method.atoms.holes import OpenPlaces
from gaussian_atoms_method.atoms.peaks import discovery_level, level_for, resolution_elements
from gaussian_atoms_method.atoms.point_response import clean_peaks, point_response
from gaussian_atoms_method.physics.noise import mad_std
from gaussian_atoms_method.physics.reconstruction import backprojection_for_peaks


def unexplained_sites(
    residuals: np.ndarray,
    angles_deg: np.ndarray,
    pixel_size_A: float,
    existing_A: np.ndarray,
    sigma_A: float,
    tilt_axis: str = "y",
    centre_px=None,
    smoothing_A: float = 0.5,
    min_distance_A: float = 1.0,
    false_alarm_rate: float = 0.05,
    tilt_axis_angle_deg: float = 0.0,
    device: str = "cpu",
    hard_core_A: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Sites of significant unexplained mass, strongest first.

    Parameters
    ----------
    residuals : (N, H, W) array
        Measured minus predicted projections (any units).
    angles_deg, pixel_size_A, tilt_axis, centre_px, tilt_axis_angle_deg
        The tilt series' geometry (:func:`gaussian_atoms_method.physics.reconstruction.reconstruct`).
    existing_A : (K, 3) array
        The Gaussians already there, Å about the tilt centre (world x, y, z).
    sigma_A : float
        Width of the atom a site is taken to be, Å (for its mass).
    hard_core_A : float, optional
        The material's hard core (Å): where given, the places an atom could be are searched at
        their own level too (step 5 above).

    Returns
    -------
    positions_A : (M, 3) array
        Å about the tilt centre.
    masses : (M,) array
        Integrated mass of each, residual units x Å^2.
    """
    volume, data = _smoothed_back_projection(
        residuals, angles_deg, pixel_size_A, tilt_axis, centre_px, smoothing_A, tilt_axis_angle_deg, device
    )
    noise = mad_std(data)
    existing_A = np.asarray(existing_A, dtype=np.float64).reshape(-1, 3)
    if not noise > 0:
        return np.zeros((0, 3)), np.zeros(0)
    whole = resolution_elements(data)
    family_wise = level_for(whole, false_alarm_rate)
    search_level, is_open, part = family_wise, None, None
    if hard_core_A is not None and np.isfinite(hard_core_A) and len(existing_A):
        is_open = OpenPlaces(existing_A, hard_core_A)
        n_open = is_open.voxel_count(data.shape, volume.index_to_A)
        if n_open:
            part = max(whole * n_open / float(np.prod(data.shape)), 1.0)
            # No more peaks there than cells of min_distance_A: the lowest level the discovery rule can reach.
            cells = max(n_open * (volume.spacing_A / min_distance_A) ** 3, 1.0)
            search_level = min(family_wise, level_for(part, false_alarm_rate * cells))
    peaks = maxima.separated_maxima_device(data, volume.spacing_A, min_distance_A, search_level * noise)
    values = maxima.values_at(data, peaks) if len(peaks) else np.zeros(0)
    levels = np.full(len(peaks), family_wise)
    if part is not None and len(peaks):
        inside = is_open(volume.index_to_A(peaks))
        if inside.any():
            level = discovery_level(values[inside] / noise, part, false_alarm_rate, level_for(part, false_alarm_rate))
            levels[inside] = np.minimum(levels[inside], level)
    levels *= noise
    keep = values > levels
    peaks, values, levels = peaks[keep], values[keep], levels[keep]
    if len(peaks) == 0:
        return np.zeros((0, 3)), np.zeros(0)
    response, centre = point_response(
        residuals.shape, angles_deg, pixel_size_A, sigma_A, tilt_axis, smoothing_A, tilt_axis_angle_deg, device
    )
    accepted, values = clean_peaks(peaks, values, response, centre, levels, device)
    positions_A = volume.index_to_A(peaks[accepted])
    if len(existing_A):
        tree = is_open.tree if is_open is not None else cKDTree(existing_A)
        distance, _ = tree.query(positions_A, workers=-1)
        positions_A, values = positions_A[distance > min_distance_A], values[distance > min_distance_A]
    return positions_A, values * (2 * math.pi * (sigma_A**2 + smoothing_A**2)) ** 1.5


def _smoothed_back_projection(
    residuals, angles_deg, pixel_size_A, tilt_axis, centre_px, smoothing_A, tilt_axis_angle_deg, device
):
    """The residuals' filtered back-projection (Hann) and the same smoothed by ``smoothing_A``:
    ``(volume, data)``, the data a tensor on ``device``.  The back-projection stays there (a host
    copy of the 401^3 float64 volume and back took 0.45 s a search at 20,000 atoms on the H100
    machine), as do the filter, the noise reading and the maxima; only sites come back."""
    volume = backprojection_for_peaks(
        residuals, angles_deg, pixel_size_A, tilt_axis, centre_px, tilt_axis_angle_deg, device=device
    )
    return volume, volume_filters.gaussian_filter(
        volume_filters.as_volume(volume.data, device), smoothing_A / volume.spacing_A
    )


def open_place_peaks(
    residuals: np.ndarray,
    angles_deg: np.ndarray,
    pixel_size_A: float,
    existing_A: np.ndarray,
    hard_core_A: float,
    tilt_axis: str = "y",
    centre_px=None,
    smoothing_A: float = 0.5,
    tilt_axis_angle_deg: float = 0.0,
    device: str = "cpu",
) -> np.ndarray:
    """(M, 3) Å about the tilt centre: every place an atom could be (inside the material, at least
    ``hard_core_A`` from every one of the Gaussians ``existing_A`` and from each other:
    :class:`~.holes.OpenPlaces`) where the residuals' smoothed back-projection (step 1 of
    :func:`unexplained_sites`) has a local maximum of positive mass, strongest first.

    Proposals, not findings: no level but the sign, as a fit started again from them judges each
    (:meth:`~gaussian_atoms_method.engine.fit.AtomFit.start_again`).  A light atom whose
    neighbours took up its mass leaves a weak peak: on carbon phase images at 2,000 e/Å² the
    missed atoms' peaks reached a median 2.0 noise standard deviations, under any level noise
    alone keeps below in a volume, and 0.87 of the missed atoms lay within 0.75 Å of such a
    place (0.70 with a level of 2 standard deviations)."""
    existing_A = np.asarray(existing_A, dtype=np.float64).reshape(-1, 3)
    if len(existing_A) == 0 or not np.isfinite(hard_core_A) or hard_core_A <= 0:
        return np.zeros((0, 3))
    volume, data = _smoothed_back_projection(
        residuals, angles_deg, pixel_size_A, tilt_axis, centre_px, smoothing_A, tilt_axis_angle_deg, device
    )
    peaks = maxima.separated_maxima_device(data, volume.spacing_A, hard_core_A, 0.0)
    places = volume.index_to_A(peaks) if len(peaks) else np.zeros((0, 3))
    return places[OpenPlaces(existing_A, hard_core_A)(places)]
