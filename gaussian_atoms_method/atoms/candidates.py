"""Candidate atom sites from a tilt series' filtered back-projection, strongest first.

The paper starts from random positions and relies on duplication to reach every atom; on the
6,679-atom Au particle that left 6-10% of the atoms with no Gaussian near them.  A
back-projection already shows where the mass is.  The search runs as named steps on one
:class:`CandidateSearch` (:data:`CANDIDATE_STEPS`):

1. back-projection with a Hann filter (:func:`backproject`);
2. smoothing with a Gaussian of ``smoothing_A``, a matched filter for atom-shaped peaks;
3. local maxima strongest first, ``min_distance_A`` apart and above the level the
   back-projected noise reaches anywhere with chance ``false_alarm_rate``, accepted CLEAN-style
   (each judged less the responses of the stronger ones): as many as the data hold, no cap;
4. shoulders: maxima of the Laplacian of Gaussian away from the candidates (a light atom beside
   a heavy one);
5. the finest scale the detector samples: Laplacian maxima half a bond from every candidate
   (two bonded light atoms make one smoothed peak);
6. remainders: sites the candidates' fitted responses leave unexplained (an atom that is a
   neighbour's shoulder at every scale).

The measurements behind each step are in the history of ``CHANGELOG.md`` ("The start's six steps").
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.spatial import cKDTree

from gaussian_atoms_method.atoms import volume_filters
from gaussian_atoms_method.atoms.deconvolution import matched_response, peak_sharpness, remainder_sites
from gaussian_atoms_method.atoms.maxima import separated_maxima_device, values_at
from gaussian_atoms_method.atoms.peaks import random_field_threshold
from gaussian_atoms_method.atoms.point_response import backprojected_atom, clean_peaks, point_response
from gaussian_atoms_method.physics.noise import NoiseModel, noise_from_projections
from gaussian_atoms_method.physics.reconstruction import Volume, backprojection_for_peaks, reconstruct

BRIGHT_PIXELS_PERCENTILE = 99.0
"""Step 5's maxima lie on the atoms' own signal (between bonded neighbours), where counting
noise is highest, so its level takes the noise variance of the brightest 1% of the pixels, not
the mean (the same for additive noise): with the mean, Poisson counts gained candidates made of
the brighter pixels' own noise, which the run then kept as false atoms."""


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
        from scipy import ndimage

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


@dataclass
class CandidateSearch:
    """What the steps of :func:`backprojection_candidates` share: the inputs, what each step
    made, and the candidates so far ((M, 3) voxel indices of ``volume``, strongest first)."""

    projections: np.ndarray
    angles_deg: np.ndarray
    pixel_size_A: float
    tilt_axis: str
    centre_px: object
    tilt_axis_angle_deg: float
    device: str
    max_count: int | None
    smoothing_A: float
    min_distance_A: float
    shoulders: bool
    shoulder_strength: float
    false_alarm_rate: float
    fine_scale_A: float | None
    fine_min_distance_A: float
    noise: NoiseModel | None
    deconvolve: bool
    slice_size_px: int | None
    volume: Volume | None = None
    data: torch.Tensor | None = None
    laplacian: torch.Tensor | None = None
    level: float = -math.inf
    sample: np.ndarray | None = None
    variance: np.ndarray | None = None
    positions: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), dtype=np.int64))
    fine: object = None
    fine_level: float = -math.inf
    fine_maxima: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), dtype=np.int64))
    resolved: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), dtype=np.int64))

    @property
    def counted(self) -> bool:
        """Whether the candidates are as many as stand above the noise (no ``max_count``)."""
        return self.max_count is None

    @property
    def sigma_vox(self) -> float:
        return self.smoothing_A / self.volume.spacing_A

    def on_host(self, filtered):
        """A filter of tensors applied to a (small) host array: the noise sample."""
        return lambda v: filtered(volume_filters.as_volume(v, self.device, None)).cpu().numpy()

    def smooth(self, v):
        """The matched filter: the data and the noise sample go through the same one."""
        return volume_filters.gaussian_filter(v, self.sigma_vox) if self.smoothing_A > 0 else v

    def fine_filter(self, v):
        """Step 5's Laplacian at the finest scale the detector samples: the data and the noise
        sample through the same one."""
        scale = self.fine_scale_A
        fine_vox = max(scale / self.volume.spacing_A, 1.0) if scale is not None else 1.0
        return -volume_filters.gaussian_laplace(v, fine_vox)


def backproject(search: CandidateSearch, backprojection: Volume | None) -> None:
    """Step 1: the filtered back-projection (or the one given), cut back to the detector's depth
    where it was made wider across the tilt axis."""
    s = search
    if backprojection is None:
        volume = backprojection_for_peaks(
            s.projections, s.angles_deg, s.pixel_size_A, s.tilt_axis, s.centre_px, s.tilt_axis_angle_deg,
            s.slice_size_px, s.device,
        )  # fmt: skip
    else:
        volume = Volume(
            torch.as_tensor(backprojection.data, device=s.device), backprojection.spacing_A, backprojection.origin_index
        )
    if s.slice_size_px is not None:  # wider across the axis only: the depth back to the detector's length
        depth = s.projections.shape[1 if s.tilt_axis == "y" else 2] | 1
        start = int(volume.origin_index[2]) - depth // 2
        volume = Volume(
            volume.data[:, :, max(start, 0) : start + depth].contiguous(),
            volume.spacing_A,
            volume.origin_index - np.array([0.0, 0.0, max(start, 0)]),
        )
    s.volume = volume


def _smooth(search: CandidateSearch) -> None:
    """Step 2: the matched filter (and step 4's Laplacian, sharing two of its three passes)."""
    s = search
    if s.shoulders and s.smoothing_A > 0 and s.counted:
        s.data, s.laplacian = volume_filters.gaussian_filter_and_laplace(s.volume.data, s.sigma_vox)
        s.laplacian.neg_()
    else:
        s.data = s.smooth(s.volume.data)


def _noise_level(search: CandidateSearch) -> None:
    """The level the back-projected noise's maxima stay below (only when counting)."""
    s = search
    if s.counted:
        s.sample, s.variance = backprojected_noise(
            s.projections, s.angles_deg, s.pixel_size_A, s.tilt_axis, s.device, noise=s.noise
        )
        s.level = noise_level(
            s.sample, math.sqrt(float(s.variance.mean())), s.on_host(s.smooth), s.false_alarm_rate, s.data.numel()
        )


def _strongest_maxima(search: CandidateSearch) -> None:
    """Step 3: maxima above the level, strongest first (a maximum above the level is only ever
    suppressed by a stronger one), then one candidate per atom, not one per maximum of its
    ridge (CLEAN)."""
    s = search
    positions = separated_maxima_device(s.data, s.volume.spacing_A, s.min_distance_A, s.level)
    if s.counted and len(positions):
        response, centre = point_response(
            s.projections.shape, s.angles_deg, s.pixel_size_A, s.smoothing_A, s.tilt_axis, s.smoothing_A,
            s.tilt_axis_angle_deg, s.device,
        )  # fmt: skip
        positions = positions[
            clean_peaks(positions, values_at(s.data, positions), response, centre, s.level, s.device)[0]
        ]
    s.positions = positions[: s.max_count]


def _shoulders(search: CandidateSearch) -> None:
    """Step 4: Laplacian-of-Gaussian maxima away from the candidates, above a fraction of the
    Laplacian at the candidates (light atoms on a heavy one's shoulder)."""
    s = search
    if not (s.shoulders and s.smoothing_A > 0 and (s.counted or len(s.positions) < s.max_count)):
        return
    laplacian = s.laplacian if s.laplacian is not None else -volume_filters.gaussian_laplace(s.volume.data, s.sigma_vox)
    # Only maxima above the strength cut can be kept, and one is only ever suppressed by a
    # stronger one, so the search starts at the cut (a few thousand voxels, not half the volume).
    positions = s.positions
    strength = s.shoulder_strength * np.percentile(values_at(laplacian, positions), 90) if len(positions) else -math.inf
    extra = separated_maxima_device(laplacian, s.volume.spacing_A, s.min_distance_A, strength)
    if len(positions) and len(extra):
        distance, _ = cKDTree(positions * s.volume.spacing_A).query(extra * s.volume.spacing_A, workers=-1)
        extra = extra[(distance > s.min_distance_A) & (values_at(laplacian, extra) >= strength)]
    s.laplacian = None
    s.positions = np.concatenate([positions, extra])[: s.max_count]


def _fine_maxima(search: CandidateSearch) -> None:
    """Step 5: maxima of the Laplacian at the finest scale the detector samples, more than
    ``fine_min_distance_A`` from every candidate (bonded light atoms)."""
    s = search
    if not (s.counted and len(s.positions) and s.fine_scale_A != 0):
        return
    s.fine = s.fine_filter(s.volume.data)
    s.fine_level = noise_level(
        s.sample,
        math.sqrt(percentile(s.variance, BRIGHT_PIXELS_PERCENTILE)),
        s.on_host(s.fine_filter),
        s.false_alarm_rate,
        s.data.numel(),
    )
    s.fine_maxima = separated_maxima_device(s.fine, s.volume.spacing_A, s.fine_min_distance_A, s.fine_level)
    if len(s.fine_maxima):
        distance, _ = cKDTree(s.positions * s.volume.spacing_A).query(s.fine_maxima * s.volume.spacing_A, workers=-1)
        s.resolved = s.fine_maxima[distance > s.fine_min_distance_A]
        s.positions = np.concatenate([s.positions, s.resolved])
    if not (s.deconvolve and len(s.resolved)):
        s.fine = None  # step 6 reads it only where step 5 added sites


def _remainders(search: CandidateSearch) -> None:
    """Step 6 (after step 5 added sites): the sites the candidates' fitted responses leave
    unexplained."""
    s = search
    if not (s.deconvolve and len(s.resolved)):
        return
    # off the CPU the fit and its maxima stay on the device
    fine = s.fine.numpy() if s.fine.device.type == "cpu" else s.fine
    narrow_A = max(0.3, 0.7 * s.pixel_size_A)  # sampled by the detector
    narrow = backprojected_atom(
        s.projections.shape, s.angles_deg, s.pixel_size_A, narrow_A, s.tilt_axis, s.tilt_axis_angle_deg, s.device
    ).data
    # the strongest quarter: atoms
    sharpness = float(np.median(peak_sharpness(fine, s.fine_maxima[: max(len(s.fine_maxima) // 4, 1)])))
    response, centre, _ = matched_response(narrow, narrow_A, s.volume.spacing_A, s.on_host(s.fine_filter), sharpness)
    extra = remainder_sites(
        fine, s.positions, response, centre, s.volume.spacing_A, s.fine_min_distance_A, s.fine_level
    )
    s.positions = np.concatenate([s.positions, extra])
    s.fine = None


CANDIDATE_STEPS = (
    ("smoothing", _smooth),
    ("noise level", _noise_level),
    ("strongest maxima", _strongest_maxima),
    ("shoulders", _shoulders),
    ("finest scale", _fine_maxima),
    ("remainders", _remainders),
)
"""The steps after the back-projection, in order, by name (module text: steps 2-6)."""


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
        Add Laplacian-of-Gaussian maxima away from the smoothed peaks (step 4).
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
    search = CandidateSearch(
        projections, angles_deg, pixel_size_A, tilt_axis, centre_px, tilt_axis_angle_deg, device, max_count,
        smoothing_A, min_distance_A, shoulders, shoulder_strength, false_alarm_rate, fine_scale_A, fine_min_distance_A,
        noise, deconvolve, slice_size_px,
    )  # fmt: skip
    backproject(search, backprojection)
    for _name, step in CANDIDATE_STEPS:
        step(search)
    positions_A = search.volume.index_to_A(search.positions)
    return (positions_A, values_at(search.data, search.positions)) if return_values else positions_A
