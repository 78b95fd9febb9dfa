"""Atoms that no maximum shows: the candidates' fitted responses taken off a sharp filter of the
back-projection, and the maxima of what is left (the start's step 6, :mod:`.candidates`).

An atom that is a shoulder of a bonded neighbour at every scale has no maximum of its own (97
of the 7,000-atom carbon's atoms at noise 5, never recovered by the fit).  So:

1. each candidate's response through the same filter, at the atom width the data show
   (:func:`matched_response`), placed at its sub-voxel peak (:func:`subvoxel_peaks`), is fitted
   to the field with every amplitude at once (:func:`fit_amplitudes`, conjugate gradients);
2. the maxima of the remainder, more than ``min_distance_A`` from each other and from every
   candidate, are the sites the candidates do not explain, kept above the level the fit's own
   error reaches: the remainder's negative side, which the error makes as often as the positive
   and a missing atom never does, counts the error's maxima at each height (*decoys*, as in a
   target-decoy estimate of the false discovery rate, :func:`decoy_level`).

The measurements behind the step count and the decoy level: the history of ``CHANGELOG.md`` ("Docstrings'
measurements").
"""

from __future__ import annotations

import math

import numpy as np
import scipy
from scipy.spatial import cKDTree

from gaussian_atoms_method.atoms.maxima import separated_maxima_device, separated_maxima_host, values_at
from gaussian_atoms_method.atoms.peaks import parabola_vertex
from gaussian_atoms_method.atoms.point_response import peak_normalised

DECOY_FALSE_DISCOVERY_RATE = 0.25
"""At most this share of the sites kept may be expected to be the model's error (the decoys'
count over the sites' count).  The sites are a start for the fit, whose final prune judges every
Gaussian by its own significance, so the list need only be mostly atoms: the start's steps 1-5
already give the fit 26-43% of surplus candidates on the carbon.  Measured on the carbon at
noise 5 this keeps all 97 missing atoms with 26 others; at noise 20 the level is the noise's
(6.7), which keeps 254 of 277 (0.1 would keep 215)."""


def _reader(field):
    """A function of (M, 3) voxel indices giving ``field``'s values there: an array's own
    indexing, or for a tensor a gather on its device (:func:`.maxima.values_at`)."""
    if isinstance(field, np.ndarray):
        return lambda indices: field[tuple(indices.T)]
    return lambda indices: values_at(field, indices)


def _face_neighbours(field, indices: np.ndarray):
    """Per axis, ``field`` (an array or a tensor) at each (M, 3) voxel's two face neighbours
    along it (below, above), clipped to the volume."""
    last, read = np.array(field.shape) - 1, _reader(field)
    for axis in range(3):
        step = np.zeros(3, dtype=np.int64)
        step[axis] = 1
        yield read(np.clip(indices - step, 0, last)), read(np.clip(indices + step, 0, last))


def peak_sharpness(field, peaks: np.ndarray) -> np.ndarray:
    """At each (M, 3) voxel of ``peaks``: the mean of ``field`` (an array or a tensor) at the
    six face neighbours over its value there (1 for a flat field, lower for a sharper peak)."""
    peaks = np.asarray(peaks, dtype=np.int64).reshape(-1, 3)
    around = np.zeros(len(peaks))
    for below, above in _face_neighbours(field, peaks):
        around += below
        around += above
    return around / 6.0 / _reader(field)(peaks)


def matched_response(
    narrow: np.ndarray, narrow_sigma_A: float, spacing_A: float, sharp, sharpness: float, max_width_A: float = 1.2
) -> tuple[np.ndarray, np.ndarray, float]:
    """One atom through the filter ``sharp``, at the width the data show.

    ``narrow`` is the back-projection of an atom of width ``narrow_sigma_A``
    (:func:`~.point_response.backprojected_atom`); an atom of width ``w`` gives it blurred by
    ``sqrt(w^2 - narrow^2)``.  The width is the one whose response's :func:`peak_sharpness`
    equals the data's ``sharpness`` (read the same way at the data's strongest maxima of the
    same filter): the shape of the peak within one voxel, which a neighbour a bond away barely
    touches (a ratio of the filtered to the plain back-projection is not: the neighbours, drawn
    out along the missing wedge, add to the plain value).  Why the width is read and not
    assumed: with a response too narrow each atom's remainder is a positive shell around it,
    whose maxima clear the level.  Returns the response scaled to
    1 at its peak, the peak's voxel and the width in Å (within ``narrow_sigma_A``-``max_width_A``)."""
    widths = np.arange(narrow_sigma_A, max_width_A + 1e-9, 0.05)

    def response(width, volume=narrow):
        return peak_normalised(
            sharp(scipy.ndimage.gaussian_filter(volume, math.sqrt(max(width**2 - narrow_sigma_A**2, 0.0)) / spacing_A))
        )

    # the search reads only the peak: a box of 4 widest blurs about it (an eighth of the volume's cost)
    centre = np.array(np.unravel_index(int(np.argmax(narrow)), narrow.shape))
    half = int(math.ceil(4 * max_width_A / spacing_A))
    box = narrow[tuple(slice(max(c - half, 0), c + half + 1) for c in centre)]
    values = [float(peak_sharpness(*response(width, box))[0]) for width in widths]  # rises with the width
    width = float(np.interp(sharpness, values, widths))
    return (*response(width), width)


def subvoxel_peaks(field, indices: np.ndarray) -> np.ndarray:
    """(M, 3) float voxel positions of the peaks of ``field`` (an array, or a tensor read on its
    device) near the integer ``indices`` (M, 3): a parabola through each voxel and its two
    neighbours along each axis (:func:`~.peaks.parabola_vertex`: clipped to half a voxel, 0
    where not concave)."""
    indices = np.asarray(indices, dtype=np.int64)
    centre = _reader(field)(indices)
    offsets = np.stack(
        [parabola_vertex(below, centre, above) for below, above in _face_neighbours(field, indices)], axis=1
    )
    return indices + offsets


def _wrapped_kernel(response: np.ndarray, centre, shape) -> np.ndarray:
    """``response`` wrapped onto a float32 volume of ``shape`` with ``centre`` at the origin (cut
    to the volume where it is larger), for circular convolution."""
    centre = np.asarray(centre, dtype=np.int64)
    lo = np.maximum(centre - (np.array(shape) - 1) // 2, 0)
    hi = np.minimum(centre + np.array(shape) // 2 + 1, response.shape)
    cut = response[tuple(slice(a, b) for a, b in zip(lo, hi))]
    kernel = np.zeros(shape, dtype=np.float32)
    kernel[tuple(slice(0, n) for n in cut.shape)] = cut
    return np.roll(kernel, tuple(-(centre - lo)), axis=(0, 1, 2))


def _kernel_spectrum(response: np.ndarray, centre, shape) -> np.ndarray:
    """The real FFT of :func:`_wrapped_kernel`."""
    return scipy.fft.rfftn(_wrapped_kernel(response, centre, shape), workers=-1)


def _trilinear_corners(positions_vox: np.ndarray, field_shape, shape) -> tuple[np.ndarray, np.ndarray]:
    """Each (M, 3) sub-voxel position's eight trilinear corners as flat indices into a volume of
    ``shape`` (clipped to ``field_shape``) and their weights, corner by corner: (8 M,) each."""
    base = np.floor(positions_vox).astype(np.int64)
    fraction = positions_vox - base
    last = np.array(field_shape) - 1
    flat, weights = [], []
    for corner in np.ndindex(2, 2, 2):
        c = np.array(corner)
        flat.append(np.ravel_multi_index(tuple(np.clip(base + c, 0, last).T), shape))
        weights.append(np.prod(np.where(c == 1, fraction, 1 - fraction), axis=1))
    return np.concatenate(flat), np.concatenate(weights)


def _conjugate_gradients(amplitudes, gradient, normal, iterations: int) -> None:
    """``iterations`` conjugate-gradient steps on the normal equations ``A^T A a = A^T b``, in
    place on ``amplitudes`` (and ``gradient``, ``A^T (b - A a)`` at the start); ``normal``
    applies ``A^T A``.  Arrays or tensors alike (:func:`fit_amplitudes`, :func:`fit_amplitudes_on_device`)."""
    direction = gradient.copy() if isinstance(gradient, np.ndarray) else gradient.clone()
    norm = float(gradient @ gradient)
    for _ in range(iterations):
        image = normal(direction)
        curvature = float(direction @ image)
        if norm == 0.0 or curvature <= 0.0:
            break
        step = norm / curvature
        amplitudes += step * direction
        gradient -= step * image
        new_norm = float(gradient @ gradient)
        direction, norm = gradient + new_norm / norm * direction, new_norm


def fit_amplitudes(
    field: np.ndarray, positions_vox: np.ndarray, response: np.ndarray, centre, iterations: int = 2
) -> tuple[np.ndarray, np.ndarray]:
    """Amplitudes of ``response`` (peak 1 at voxel ``centre``) placed at each of the (M, 3)
    sub-voxel ``positions_vox`` (trilinear weights) that fit ``field`` best in least squares,
    all at once (``iterations`` conjugate-gradient steps on the normal equations, from the
    field's values at the positions).  Returns the (M,) amplitudes and the fitted model, a
    volume like ``field``.

    The convolutions are circular, on the volume padded to a length the FFT is fast for (a
    prime length is several times slower); the normal
    operator is one convolution with the response's autocorrelation, so each step costs one
    pair of transforms."""
    shape = tuple(scipy.fft.next_fast_len(n, real=True) for n in field.shape)
    spectrum = _kernel_spectrum(response, centre, shape)
    power = (spectrum * np.conj(spectrum)).real.astype(np.float32)
    last = np.array(field.shape) - 1
    flat, weights = _trilinear_corners(positions_vox, field.shape, shape)
    count = len(positions_vox)

    def splat(amplitudes):
        spikes = np.bincount(flat, weights=np.tile(amplitudes, 8) * weights, minlength=int(np.prod(shape)))
        return scipy.fft.rfftn(spikes.reshape(shape).astype(np.float32), workers=-1)

    def sample(spectrum_):
        volume = scipy.fft.irfftn(spectrum_, s=shape, workers=-1).ravel()
        return (weights * volume[flat]).reshape(8, count).sum(axis=0)

    def normal(amplitudes):  # A^T A a
        return sample(splat(amplitudes) * power)

    padded = np.zeros(shape, dtype=np.float32)
    padded[tuple(slice(0, n) for n in field.shape)] = field
    amplitudes = np.asarray(field[tuple(np.rint(positions_vox).astype(np.int64).clip(0, last).T)], dtype=np.float64)
    gradient = sample(scipy.fft.rfftn(padded, workers=-1) * np.conj(spectrum)) - normal(amplitudes)
    _conjugate_gradients(amplitudes, gradient, normal, iterations)
    model = scipy.fft.irfftn(splat(amplitudes) * spectrum, s=shape, workers=-1)
    return amplitudes, model[tuple(slice(0, n) for n in field.shape)]


def fit_amplitudes_on_device(field, positions_vox: np.ndarray, response: np.ndarray, centre, iterations: int = 2):
    """:func:`fit_amplitudes` of a 3D float32 tensor ``field``, on its device (torch's FFTs, the
    splats and samples as index-adds and gathers): the same steps in the same precisions, so
    the same amplitudes to float rounding (tests compare them on the CPU).  Returns the (M,)
    amplitudes (an array) and the fitted model (a tensor like ``field``): at tens of thousands
    of atoms the host's version was a large part of a GPU run's start."""
    import torch

    dev = field.device
    shape = tuple(scipy.fft.next_fast_len(n, real=True) for n in field.shape)
    spectrum = torch.fft.rfftn(torch.as_tensor(_wrapped_kernel(response, centre, shape), device=dev))
    power = (spectrum * spectrum.conj()).real
    flat, weights = (torch.as_tensor(x, device=dev) for x in _trilinear_corners(positions_vox, field.shape, shape))
    count, size = len(positions_vox), int(np.prod(shape))
    # Corners that share a voxel are summed in one fixed order, not by index_add_, whose atomic
    # adds on a GPU sum them in whatever order the threads land.  (On an H200 the start's weights
    # on Ta sub-area 23 still differ between processes with this: another source remains.)
    order = torch.argsort(flat, stable=True)
    voxels, shared = torch.unique_consecutive(flat[order], return_counts=True)
    starts = torch.cumsum(shared, 0) - shared
    rounds = []  # round k: every voxel's k-th corner (each voxel once a round)
    for k in range(int(shared.max()) if len(shared) else 0):
        held = torch.nonzero(shared > k).squeeze(1)
        rounds.append((held, starts[held] + k))

    def splat(amplitudes):
        corners = (amplitudes.repeat(8) * weights)[order]
        sums = torch.zeros(len(voxels), dtype=torch.float64, device=dev)
        for held, at in rounds:
            sums[held] += corners[at]
        spikes = torch.zeros(size, dtype=torch.float64, device=dev)
        spikes[voxels] = sums
        return torch.fft.rfftn(spikes.reshape(shape).float())

    def sample(spectrum_):
        volume = torch.fft.irfftn(spectrum_, s=shape).reshape(-1)
        return (weights * volume[flat]).reshape(8, count).sum(dim=0)

    def normal(amplitudes):  # A^T A a
        return sample(splat(amplitudes) * power)

    padded = torch.zeros(shape, dtype=torch.float32, device=dev)
    padded[tuple(slice(0, n) for n in field.shape)] = field
    last = torch.as_tensor(np.array(field.shape) - 1, device=dev)
    nearest = torch.as_tensor(np.rint(positions_vox).astype(np.int64), device=dev).clamp(
        min=torch.zeros_like(last), max=last
    )
    amplitudes = field[nearest[:, 0], nearest[:, 1], nearest[:, 2]].double()
    gradient = sample(torch.fft.rfftn(padded) * spectrum.conj()) - normal(amplitudes)
    _conjugate_gradients(amplitudes, gradient, normal, iterations)
    model = torch.fft.irfftn(splat(amplitudes) * spectrum, s=shape)
    return amplitudes.cpu().numpy(), model[tuple(slice(0, n) for n in field.shape)]


def decoy_level(values: np.ndarray, decoys: np.ndarray, false_discovery_rate: float) -> float:
    """The lowest height at which the ``decoys`` (heights the error alone makes) number at most
    ``false_discovery_rate`` times the ``values`` (the sites' heights) that reach it; the
    sites at or above it are kept.  ``inf`` when no height qualifies, the lowest value when
    there are no decoys."""
    values = np.sort(np.asarray(values, dtype=np.float64))[::-1]
    decoys = np.sort(np.asarray(decoys, dtype=np.float64))
    if len(values) == 0:
        return np.inf
    # at the k-th highest value v: sites >= v number k + 1, decoys >= v number len - searchsorted
    false = len(decoys) - np.searchsorted(decoys, values, side="left")
    passing = np.nonzero(false <= false_discovery_rate * np.arange(1, len(values) + 1))[0]
    return float(values[passing[-1]]) if len(passing) else np.inf


def remainder_sites(
    field: np.ndarray,
    indices: np.ndarray,
    response: np.ndarray,
    centre,
    spacing_A: float,
    min_distance_A: float,
    noise_level: float,
    false_discovery_rate: float = DECOY_FALSE_DISCOVERY_RATE,
    iterations: int = 2,
) -> np.ndarray:
    """(K, 3) voxel indices of the maxima the candidates at ``indices`` (M, 3) do not explain,
    strongest first (see the module's text).

    Parameters
    ----------
    field : 3D array, the filtered back-projection
    indices : (M, 3) int array, the candidates' voxels
    response, centre : one atom through the same filter, peak 1 at voxel ``centre``
    spacing_A : float, voxel size, Å
    min_distance_A : float, the sites lie more than this from each other and the candidates, Å
    noise_level : float, what the noise alone reaches in ``field``; no site lies below it
    false_discovery_rate : float, :data:`DECOY_FALSE_DISCOVERY_RATE`
    iterations : int, conjugate-gradient steps of :func:`fit_amplitudes`
    """
    if len(indices) == 0:
        return np.zeros((0, 3), dtype=np.int64)
    tree = cKDTree(np.asarray(indices) * spacing_A)

    def apart(peaks):  # more than min_distance_A from every candidate
        return peaks[tree.query(peaks * spacing_A)[0] > min_distance_A] if len(peaks) else peaks

    # an array on the host; a tensor on its device (the same fit and maxima, .maxima): only peaks come back
    on_host = isinstance(field, np.ndarray)
    fit, maxima = (
        (fit_amplitudes, separated_maxima_host) if on_host else (fit_amplitudes_on_device, separated_maxima_device)
    )
    _, model = fit(field, subvoxel_peaks(field, indices), response, centre, iterations)
    remainder = field - model
    del model
    sites = apart(maxima(remainder, spacing_A, min_distance_A, noise_level))
    decoys = apart(maxima(-remainder, spacing_A, min_distance_A, noise_level))
    read = _reader(remainder)
    heights = read(sites)
    return sites[heights >= decoy_level(heights, -read(decoys), false_discovery_rate)]
