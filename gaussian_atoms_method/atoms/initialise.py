"""Where the Gaussians start: candidate atom sites from a smoothed back-projection.

The paper starts from about 10,000 Gaussians at random positions and relies on gradient-driven
duplication to reach every atom.  Measured on the 6,679-atom Au particle (limited tilts), that
leaves 6-10% of the atoms with no Gaussian near them: a neighbour widens to absorb an empty
site's signal and the pull that would trigger duplication cancels.  A filtered back-projection
already shows where the mass is, so we start there:

1. FBP with a Hann filter (the ramp filter's high frequencies are mostly noise at atomic
   resolution);
2. smoothing with a Gaussian of ``smoothing_A`` (0.5 Å, about a blurred atom's width): a
   matched filter for atom-shaped peaks;
3. local maxima taken strongest first, at least ``min_distance_A`` apart (1.0 Å: closer than
   the shortest bond of any material, C-C 1.42 Å, so no atom is shadowed by a neighbour's
   candidate; 1.5 Å, the earlier value, could not seat two carbon neighbours), and above the
   level the back-projected noise reaches anywhere in the volume with chance
   ``false_alarm_rate`` (:func:`backprojected_noise`: noise of the measured variance through
   the same filter and smoothing; :func:`~gaussian_atoms_method.atoms.peaks.random_field_threshold`).
   How many candidates there are follows from the data; there is no cap unless ``max_count``
   is given (the paper's fixed 10,000 left a 20,000-atom particle at TPR 0.38).  On the
   6,679-atom Au series (limited tilts, noise 200) every atom's smoothed back-projection
   stands at least 19.5 noise standard deviations high; the level is about 5, and 9,980
   maxima clear it (the rest are the missing wedge's streaks of the atoms themselves, which
   the fit prunes).  So the maxima above the level are then accepted CLEAN-style
   (:func:`~gaussian_atoms_method.atoms.point_response.clean_peaks`): strongest first, each
   judged on its value less the responses of the atoms accepted before it.  On the Au series at
   noise 500 that keeps 6,828 of 7,231 maxima, halves the candidates with no atom within
   0.75 Å (753 -> 373), and keeps the recall (0.9672 -> 0.9659): a surplus candidate on an
   atom's ridge becomes a second Gaussian that shares the atom and is lost with it.

Measured recall (a candidate within 1.2 Å of every true atom, 10,000 candidates, Au limited,
Lobato potentials): 1.000 at noise 50, 0.9998 at noise 200, 0.994 at noise 500; the ramp
filter without smoothing reaches 0.83 and 0.46 at noise 200 and 500.  Surplus candidates are
noise: the fit drives their mass down and the prune removes them.

4. In mixed particles a light atom beside a heavy one is often only a shoulder of the heavy
   atom's smoothed peak, not a maximum.  Maxima of the negative Laplacian of Gaussian (same
   0.5 Å scale, which sharpens shoulders into peaks) that lie more than ``min_distance_A``
   from every smoothed-peak candidate, and are strong (at least ``shoulder_strength`` = 0.35
   of the 90th percentile of the Laplacian at the smoothed peaks) are added (within
   ``max_count`` when one is given).  Measured on the half-size HEA particle (limited tilts): of the 86
   atoms (noise 50) and 121 (noise 200) that no smoothed peak reaches, about 75 and 90 gain a
   candidate, with few or no spurious ones.  Without the strength cut, the Laplacian's weak
   maxima between the atoms of a crystal (2,200 on the 999-atom FePt particle at noise 50,
   none of them atoms) cost FePt 0.7% of its TPR and 2 pm.
5. Two bonded light atoms (C-C 1.42-1.55 Å, each blurred to about 0.65 Å) make one peak of the
   0.5 Å matched filter, between them, and the 0.5 Å Laplacian's maxima then lie within
   ``min_distance_A`` of it: the start held one candidate for both, the fit kept one Gaussian
   for both (the pulls of the two atoms cancel, so duplication never split it), and on the
   7,000-atom disordered carbon (tilts -72:4:72, 0.32 Å pixels) the final TPR equalled the
   start's recall, 0.94 at noise 5.  So maxima of the Laplacian at the finest scale the data are
   sampled at (``fine_scale_A``, one voxel: the detector pixel) that stand above that filter's own
   noise level (:func:`noise_level`, random-field level at ``false_alarm_rate``, as step 3)
   and lie more than ``fine_min_distance_A`` from each other and from every candidate are
   added.  That distance is half the shortest bond (0.7 Å), not ``min_distance_A``: the blur
   pulls two bonded atoms' maxima towards each other and the earlier candidate sits between
   them, so 1 Å kept the neighbour's maximum out for 193 of the 7,000 carbon atoms (its
   maximum 0.4 Å from the atom, under 1 Å from the candidate); two atoms a bond apart are never
   one maximum each closer than half a bond to the other's.  The filter's noise is higher
   than the matched filter's, so it adds only where the dose resolves the neighbour
   (its level: :data:`BRIGHT_PIXELS_PERCENTILE`).
   Measured, start recall within 0.75 Å, then final TPR / false per atom (before -> after):
   carbon noise 5 0.9399 -> 0.9861, 0.9411 / 0.0001 -> 0.9873 / 0.0003; carbon noise 20
   0.9116 -> 0.9604, 0.9137 / 0.0020 -> 0.9621 / 0.0030 (H100); HEA noise 50 +23 candidates,
   0.9940 / 0.0035 -> 0.9965 / 0.0020; Au noise 50 +410 candidates (surplus on the missing
   wedge's streaks), same scores (this CPU); Au noise 200 and 500, HEA noise 200, the aSi-208
   counts: none added (CHANGELOG.md).
6. An atom that is a neighbour's shoulder at every scale has no maximum at all (carbon noise 5:
   97 atoms, each 1.2-1.45 Å from the candidate on its bonded neighbour, after step 5).  So the
   candidates' responses through step 5's filter, at the atom width the data show, are fitted
   to that field with every amplitude at once and taken off it; the maxima of what is left,
   above step 5's noise level and a level that the fit's own error (read from the remainder's
   negative side) makes unlikely, half a bond from everything, are added
   (:mod:`~gaussian_atoms_method.atoms.deconvolution`).  Only where step 5 adds candidates:
   where no maximum of the pixel-scale filter away from the candidates clears its noise, the
   dose does not resolve atoms at that scale beyond the smoothed peaks, and on every dataset
   measured step 6 then found none either (Au at noise 200 and 500, HEA at 200, the Au and
   aSi-208 counts); skipping it there saves 2.4 s of the Au start (this CPU), where the
   time to accuracy is counted.  Start recall within 0.75 Å, this CPU (candidates added): carbon noise 5
   0.9861 -> 1.0 (116), noise 20 0.9604 -> 0.994 (296); HEA noise 50 0.9915 -> 0.9975 (27);
   Au noise 50 (8), FePt noise 50 (2), aPd noise 50 (18) at recall 1.0; none at noise 200 or
   500, on the Au counts or on the aSi-208 counts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage
from scipy.spatial import cKDTree

from gaussian_atoms_method.atoms import volume_filters
from gaussian_atoms_method.atoms.deconvolution import matched_response, peak_sharpness, remainder_sites
from gaussian_atoms_method.atoms.maxima import separated_maxima_device, values_at
from gaussian_atoms_method.atoms.peaks import random_field_threshold
from gaussian_atoms_method.atoms.point_response import backprojected_atom, clean_peaks, point_response
from gaussian_atoms_method.physics.devices import default_device
from gaussian_atoms_method.physics.field_of_view import FieldOfView, field_of_view
from gaussian_atoms_method.physics.noise import NoiseModel, measure_noise, noise_from_projections
from gaussian_atoms_method.physics.reconstruction import Volume, backprojection_for_peaks, reconstruct
from gaussian_atoms_method.physics.units import Normalisation

BRIGHT_PIXELS_PERCENTILE = 99.0
"""Step 5's maxima lie on the atoms' own signal (between bonded neighbours), where counting
noise is highest, so its level takes the noise variance of the brightest 1% of the pixels, not
the mean (the same for additive noise).  With the mean, Au as Poisson counts (20 and 80 at the
brightest pixel) gained 51 and 226 candidates made of that noise, and at 20 counts the run
ended with 0.021 false atoms per atom instead of 0.007; with this level none were added, and
the carbon gains stayed (start recall 0.9861 and 0.9604)."""


def backprojected_noise(
    projections: np.ndarray,
    angles_deg: np.ndarray,
    pixel_size_A: float,
    tilt_axis: str,
    device: str = "cpu",
    seed: int = 0,
    size_px: int = 64,
    noise: NoiseModel | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """A sample of the Hann back-projection of the projections' noise alone: the volume of unit
    white noise on a ``size_px`` detector of the same pixels and tilts, and the (V, H, W) noise
    variance of each pixel of the projections, which scales it (:func:`noise_level` filters the
    sample as the data are filtered and reads the level; an array, or off the CPU a float64
    tensor on ``device``).

    The noise is read from the projections (:func:`gaussian_atoms_method.physics.noise.noise_from_projections`:
    additive, Poisson or both; each pixel's variance at its smoothed value), unless ``noise``
    (a :class:`~gaussian_atoms_method.physics.noise.NoiseModel` in the projections' units)
    gives it.  A parallel-beam
    back-projection of stationary noise is stationary, so the small detector gives the spread
    (and the smoothness) of the full one's noise at a fraction of the cost."""
    p = np.asarray(projections, dtype=np.float64)
    noise = noise_from_projections(p) if noise is None else noise
    if torch.device(device).type == "cpu":
        variance = np.clip(noise.variance(ndimage.gaussian_filter(p, (0, 2.0, 2.0))), 0.0, None)
    # the same filter on the device (0.45 s on the host at 20,000 atoms on the H100 machine); a float64 tensor there
    else:
        variance = noise.variance(
            volume_filters.gaussian_filter(volume_filters.as_volume(p, device), 2.0, axes=(1, 2))
        ).clamp_min(0.0)
    h, w = min(size_px, p.shape[1]), min(size_px, p.shape[2])
    draw = np.random.default_rng(seed).standard_normal((p.shape[0], h, w))
    volume = reconstruct(draw, angles_deg, pixel_size_A, "fbp", tilt_axis, None, filter_name="hann", device=device)
    return volume.data, variance


def percentile(values, q: float) -> float:
    """``np.percentile(values, q)`` (linear interpolation) of an array, or of a tensor on its
    device (one sort there)."""
    if not isinstance(values, torch.Tensor):
        return float(np.percentile(values, q))
    ordered = values.reshape(-1).sort().values
    position = q / 100.0 * (len(ordered) - 1)
    lo = int(math.floor(position))
    hi = min(lo + 1, len(ordered) - 1)
    a, b = float(ordered[lo]), float(ordered[hi])
    return a + (b - a) * (position - lo)


def noise_level(sample: np.ndarray, scale: float, filtered, false_alarm_rate: float, n_voxels: int) -> float:
    """The height that noise, filtered by ``filtered`` (a function of a volume), reaches anywhere in
    a volume of ``n_voxels`` with chance ``false_alarm_rate``: the random-field level
    (:func:`~gaussian_atoms_method.atoms.peaks.random_field_threshold`) of the filtered noise
    ``sample`` of :func:`backprojected_noise`, read in its middle (away from the edges the
    filter sees), times its spread and the projections' noise ``scale``."""
    data = filtered(sample)
    middle = data[tuple(slice(n // 4, n - n // 4) for n in data.shape)]
    return random_field_threshold(middle, false_alarm_rate, n_voxels) * float(middle.std()) * scale


def backprojection_candidates(
    projections: np.ndarray,
    angles_deg: np.ndarray,
    pixel_size_A: float,
    tilt_axis: str = "y",
    centre_px=None,
    max_count: int | None = None,
    smoothing_A: float = 0.5,
    min_distance_A: float = 1.0,
    shoulders: bool = True,
    shoulder_strength: float = 0.35,
    device: str = "cpu",
    return_values: bool = False,
    tilt_axis_angle_deg: float = 0.0,
    false_alarm_rate: float = 0.05,
    fine_scale_A: float | None = None,
    fine_min_distance_A: float = 0.7,
    noise: NoiseModel | None = None,
    deconvolve: bool = True,
    slice_size_px: int | None = None,
    backprojection: Volume | None = None,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Candidate atom positions, strongest first.

    Parameters
    ----------
    projections : (N, H, W) array
        The tilt series (any units).
    angles_deg : (N,) array
        Single-axis tilt angles, degrees.
    pixel_size_A : float
        Detector pixel size, Å.
    tilt_axis : {"y", "x"}
    centre_px : (2,) floats, optional
        Detector (row, col) of the tilt centre; default the middle.
    max_count : int, optional
        At most this many candidates (None: as many as stand above the noise).
    smoothing_A : float
        Standard deviation of the Gaussian smoothing of the reconstruction, Å.
    min_distance_A : float
        Candidates lie more than this far apart, Å.
    shoulders : bool
        Add Laplacian-of-Gaussian maxima away from the smoothed peaks (step 4 above).
    shoulder_strength : float
        Keep only Laplacian maxima at least this fraction of the 90th percentile of the
        Laplacian at the smoothed peaks (about a heavy atom's response).
    device : str
        Where the back-projection, its filters and the search for maxima run ("cuda": the GPU;
        :mod:`.volume_filters`).
    tilt_axis_angle_deg : float
        Angle of the tilt axis in the images (:mod:`gaussian_atoms_method.physics.geometry`).
    return_values : bool
        Also return the smoothed back-projection at each candidate.
    false_alarm_rate : float
        Chance that a maximum of the noise alone anywhere in the volume clears the level
        (without ``max_count``).
    fine_scale_A : float, optional
        Scale of step 5's Laplacian of Gaussian, Å; default one voxel (the detector pixel);
        0: no step 5.
    fine_min_distance_A : float
        Step 5's maxima lie more than this far from each other and from every candidate, Å
        (0.7: half the shortest bond, C-C 1.42 Å; step 5 says why not ``min_distance_A``).
    noise : NoiseModel, optional
        The projections' noise in their units, if already read (else read here).
    deconvolve : bool
        Step 6 (with step 5): add the sites the candidates' fitted responses leave unexplained.
    slice_size_px : int, optional
        Reconstruct across the tilt axis over this many voxels (an object wider than the field of
        view, :mod:`gaussian_atoms_method.physics.field_of_view`); the depth stays the detector's.
    backprojection : Volume, optional
        Step 1's back-projection if already made
        (:func:`~gaussian_atoms_method.physics.reconstruction.backprojection_for_peaks`
        of the same arguments, on the host); else made here.

    Returns
    -------
    positions_A : (M, 3) array, M <= max_count
        Positions in Å about the tilt centre (world x, y, z), strongest first.
    values : (M,) array, only with ``return_values``
        The smoothed back-projection there (projection units per Å): about proportional to
        the atom's potential, and near zero for candidates made of noise.
    """
    if max_count is not None and max_count <= 0:
        return (np.zeros((0, 3)), np.zeros(0)) if return_values else np.zeros((0, 3))
    if backprojection is None:
        volume = backprojection_for_peaks(
            projections, angles_deg, pixel_size_A, tilt_axis, centre_px, tilt_axis_angle_deg, slice_size_px, device
        )
    else:
        volume = Volume(
            torch.as_tensor(backprojection.data, device=device), backprojection.spacing_A, backprojection.origin_index
        )
    if slice_size_px is not None:  # wider across the axis only: the depth back to the detector's length
        depth = projections.shape[1 if tilt_axis == "y" else 2] | 1
        start = int(volume.origin_index[2]) - depth // 2
        volume = Volume(
            volume.data[:, :, max(start, 0) : start + depth].contiguous(),
            volume.spacing_A,
            volume.origin_index - np.array([0.0, 0.0, max(start, 0)]),
        )
    sigma_vox = smoothing_A / volume.spacing_A
    field = volume.data

    def on_host(filtered):  # a filter of tensors applied to a (small) host array: the noise sample
        return lambda v: filtered(volume_filters.as_volume(v, device, None)).cpu().numpy()

    def smooth(v):  # the matched filter: the data and the noise sample go through the same one
        return volume_filters.gaussian_filter(v, sigma_vox) if smoothing_A > 0 else v

    laplacian = None
    if shoulders and smoothing_A > 0 and max_count is None:  # step 4's filter too, sharing two of its three passes
        data, laplacian = volume_filters.gaussian_filter_and_laplace(field, sigma_vox)
        laplacian.neg_()
    else:
        data = smooth(field)
    level = -math.inf
    if max_count is None:  # as many as stand above the back-projected noise
        sample, variance = backprojected_noise(projections, angles_deg, pixel_size_A, tilt_axis, device, noise=noise)
        level = noise_level(sample, math.sqrt(float(variance.mean())), on_host(smooth), false_alarm_rate, data.numel())
    # strongest first, so a maximum above the level is only ever suppressed by a stronger one
    positions = separated_maxima_device(data, volume.spacing_A, min_distance_A, level)
    if max_count is None:
        if len(positions):  # one candidate per atom, not one per maximum of its ridge (step 3)
            response, centre = point_response(
                projections.shape,
                angles_deg,
                pixel_size_A,
                smoothing_A,
                tilt_axis,
                smoothing_A,
                tilt_axis_angle_deg,
                device,
            )
            positions = positions[
                clean_peaks(positions, values_at(data, positions), response, centre, level, device)[0]
            ]
    positions = positions[:max_count]
    if shoulders and smoothing_A > 0 and (max_count is None or len(positions) < max_count):
        if laplacian is None:
            laplacian = -volume_filters.gaussian_laplace(field, sigma_vox)
        # Only maxima above the strength cut can be kept, and one is only ever suppressed by a
        # stronger one, so the search starts at the cut (a few thousand voxels, not half the volume).
        strength = (
            shoulder_strength * np.percentile(values_at(laplacian, positions), 90) if len(positions) else -math.inf
        )
        extra = separated_maxima_device(laplacian, volume.spacing_A, min_distance_A, strength)
        if len(positions) and len(extra):
            distance, _ = cKDTree(positions * volume.spacing_A).query(extra * volume.spacing_A, workers=-1)
            extra = extra[(distance > min_distance_A) & (values_at(laplacian, extra) >= strength)]
        del laplacian
        positions = np.concatenate([positions, extra])[:max_count]
    if max_count is None and len(positions) and fine_scale_A != 0:  # step 5: the finest scale the detector samples
        fine_vox = max(fine_scale_A / volume.spacing_A, 1.0) if fine_scale_A is not None else 1.0

        def fine_filter(v):  # the data and the noise sample through the same Laplacian
            return -volume_filters.gaussian_laplace(v, fine_vox)

        fine = fine_filter(field)
        fine_level = noise_level(
            sample,
            math.sqrt(percentile(variance, BRIGHT_PIXELS_PERCENTILE)),
            on_host(fine_filter),
            false_alarm_rate,
            data.numel(),
        )
        maxima = separated_maxima_device(fine, volume.spacing_A, fine_min_distance_A, fine_level)
        resolved = np.zeros((0, 3), dtype=np.int64)  # step 5's additions
        if len(maxima):
            distance, _ = cKDTree(positions * volume.spacing_A).query(maxima * volume.spacing_A, workers=-1)
            resolved = maxima[distance > fine_min_distance_A]
            positions = np.concatenate([positions, resolved])
        if deconvolve and len(resolved):  # step 6: what the candidates' responses leave unexplained
            # off the CPU the fit and its maxima stay on the device
            fine = fine.numpy() if fine.device.type == "cpu" else fine
            narrow_A = max(0.3, 0.7 * pixel_size_A)  # sampled by the detector
            narrow = backprojected_atom(
                projections.shape, angles_deg, pixel_size_A, narrow_A, tilt_axis, tilt_axis_angle_deg, device
            ).data
            # the strongest quarter: atoms
            sharpness = float(np.median(peak_sharpness(fine, maxima[: max(len(maxima) // 4, 1)])))
            response, centre, _ = matched_response(narrow, narrow_A, volume.spacing_A, on_host(fine_filter), sharpness)
            extra = remainder_sites(
                fine, positions, response, centre, volume.spacing_A, fine_min_distance_A, fine_level
            )
            positions = np.concatenate([positions, extra])
    positions_A = volume.index_to_A(positions)
    return (positions_A, values_at(data, positions)) if return_values else positions_A


def starting_positions(
    series,
    length_scale: float,
    count: int,
    extent: float,
    generator: torch.Generator,
    from_backprojection: bool = True,
    noise: NoiseModel | None = None,
    slice_size_px: int | None = None,
    backprojection: Volume | None = None,
    positions_A: np.ndarray | None = None,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Where training starts: (n, 3) positions in normalised units and, for a back-projection
    start, (n,) weights of mean 1 in proportion to the smoothed back-projection there (else None).

    Parameters
    ----------
    series : TiltSeries or None
        The measured tilt series (``projections``, ``angles_deg``, ``pixel_size_A``,
        ``tilt_axis``, ``centre_px``); None, or ``from_backprojection`` False: a random start.
    length_scale : float
        Normalised length per Å (:class:`~gaussian_atoms_method.physics.units.Normalisation`).
    count : int
        The number of random positions (a back-projection start takes every candidate above
        the noise, :func:`backprojection_candidates`).
    extent : float
        Side of the cube (normalised units) the random positions fill.
    generator : torch.Generator
        Draws the random positions.
    noise : NoiseModel, optional
        The projections' noise in the series' units, if already read.
    slice_size_px : int, optional
        Across the tilt axis, start over this many voxels (:func:`backprojection_candidates`).
    backprojection : Volume, optional
        The candidates' back-projection if already made (:func:`backprojection_candidates`).
    positions_A : (n, 3) array, optional
        Start at these positions (Å), with equal masses, instead.
    """
    if positions_A is not None:
        return torch.as_tensor(np.asarray(positions_A, dtype=np.float64) * length_scale, dtype=torch.float32), None
    if from_backprojection and series is not None:
        # A GPU, if there is one, does the back-projection (the model is built on the CPU).
        positions_A, values = backprojection_candidates(
            series.projections,
            series.angles_deg,
            series.pixel_size_A,
            series.tilt_axis,
            series.centre_px,
            None,
            device=default_device(),
            return_values=True,
            tilt_axis_angle_deg=series.tilt_axis_angle_deg,
            noise=noise,
            slice_size_px=slice_size_px,
            backprojection=backprojection,
        )
        if len(positions_A):
            # A candidate made of noise reads about zero; a floor of 1% of the strongest keeps
            # every weight positive (a log-amplitude) without making it atom-like.
            values = torch.as_tensor(values, dtype=torch.float64)
            values = values.clamp_min(0.01 * float(values.max().clamp_min(1e-30)))
            return torch.as_tensor(positions_A * length_scale, dtype=torch.float32), (values / values.mean()).float()
    return (torch.rand(count, 3, generator=generator) - 0.5) * extent, None


def starting_amplitude(
    projections, pixel_size_A: float | None, length_scale: float | None, n: int, sigma: float, data_range: float
) -> float:
    """3D peak (normalised units) that shares the measured mass equally among ``n`` Gaussians
    of width ``sigma`` (normalised): every Gaussian starts atom-like in total, and the fit sorts
    them.  ``projections``: (N, H, W) tensor in normalised data units.  Without data to size
    them by (any argument None): a faint 5% of a full-range projected peak."""
    if projections is None or pixel_size_A is None or length_scale is None:
        return 0.05 * data_range / (sigma * math.sqrt(2 * math.pi))
    pixel_area = (pixel_size_A * length_scale) ** 2
    mass = float(projections.double().sum(dim=(-2, -1)).mean().clamp_min(0.0)) * pixel_area
    mass_each = max(mass, 1e-12) / max(n, 1)
    return mass_each / (2 * math.pi * sigma**2) ** 1.5


EDGE_MARGIN_WIDTHS = 3.0
"""Along the tilt axis a film goes on past the detector: the volume reaches this many of the
widest atom's widths (``max_atom_sigma_A``) beyond it, where an atom still reaches the
detector's edge (99.7% of a Gaussian lies within three widths)."""


@dataclass
class Start:
    """What a run starts from: the measured noise of the normalised projections (None without
    data), the field of view, and the (n, 3) starting positions (normalised units) with their
    (n,) weights (None for a random start)."""

    noise: NoiseModel | None
    field: FieldOfView
    means: torch.Tensor
    weights: torch.Tensor | None


def compute_start(
    series,
    projections,
    normalisation: Normalisation,
    extended_object: str,
    max_atom_sigma_A: float,
    from_backprojection: bool = True,
    count: int = 0,
    extent: float = 1.0,
    generator: torch.Generator | None = None,
    noise: NoiseModel | None = None,
    backprojection: Volume | None = None,
    positions_A: np.ndarray | None = None,
) -> Start:
    """The start for a tilt series (``series``: :class:`~dataparsers.tilt_series_format.TiltSeries`,
    or None) with (V, H, W) ``projections`` in normalised data units: the noise measured once
    (the start and the data term share it), the field of view
    (:func:`~gaussian_atoms_method.physics.field_of_view.field_of_view`, ``extended_object`` its
    option) and the starting positions (:func:`~gaussian_atoms_method.atoms.initialise.starting_positions`:
    back-projection candidates, or ``count`` random ones in a cube of side ``extent`` drawn
    with ``generator``).  ``noise``: the projections' noise if already read, as
    :func:`~gaussian_atoms_method.physics.noise.measure_noise` reads it on this machine;
    ``backprojection``: the candidates' back-projection if already made
    (:func:`~gaussian_atoms_method.physics.reconstruction.backprojection_for_peaks`
    of the series, across the tilt axis over the field's ``slice_px``); ``positions_A``: start at
    these atoms (Å) instead of any candidates."""
    ls = normalisation.length_scale
    noise = measure_noise(projections) if noise is None else noise
    fov = field_of_view(series, projections, ls, extended_object, EDGE_MARGIN_WIDTHS * max_atom_sigma_A)
    generator = generator if generator is not None else torch.Generator()
    in_series_units = noise.scaled(1.0 / normalisation.data_scale) if noise is not None else None
    means, weights = starting_positions(
        series,
        ls,
        count,
        extent,
        generator,
        from_backprojection,
        in_series_units,
        fov.slice_px,
        backprojection,
        positions_A,
    )
    return Start(noise, fov, means, weights)
