"""What one atom looks like in a smoothed back-projection, and peaks taken CLEAN-style.

A limited tilt range and the filter make one atom's filtered back-projection elongated along
the missing wedge, with side lobes; on that ridge noise makes more than one local maximum, and a
list of maxima then holds one atom several times.  So maxima are accepted strongest first, as in
Högbom's CLEAN: each accepted one's response (:func:`point_response`, scaled to its value) is
taken off the values of those not yet visited, which must still clear the level.  A true
neighbour keeps its own peak after the subtraction; a maximum made of the first atom's ridge
does not.  Used by the start (:mod:`.initialise`) and the search of the residuals
(:mod:`.residual_sites`).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from gaussian_atoms_method.physics.reconstruction import reconstruct


def backprojected_atom(shape, angles_deg, pixel_size_A: float, sigma_A: float, tilt_axis="y", tilt_axis_angle_deg: float = 0.0, device: str = "cpu", half_width_A: float = 10.0):
    """The Hann-filtered back-projection (a volume) of one Gaussian atom of width ``sigma_A``
    at the tilt centre, in the geometry of a tilt series of ``shape`` (N, H, W), on a detector
    cut to ``half_width_A`` about its middle (:func:`point_response` says why).  Projection and
    filtered back-projection are linear and shift-invariant, so a wider atom's is this one
    blurred by a 3D Gaussian of the difference in quadrature."""
    n, h, w = shape
    half = int(np.ceil(half_width_A / pixel_size_A))
    h, w = min(h, 2 * half + 1), min(w, 2 * half + 1)
    ci, cj = (h - 1) / 2, (w - 1) / 2
    rows, cols = np.arange(h)[:, None] - ci, np.arange(w)[None, :] - cj
    image = np.exp(-(rows**2 + cols**2) / (2 * (sigma_A / pixel_size_A) ** 2))
    return reconstruct(np.repeat(image[None], n, axis=0), angles_deg, pixel_size_A, "fbp", tilt_axis, None, filter_name="hann", device=device, tilt_axis_angle_deg=tilt_axis_angle_deg)


def point_response(shape, angles_deg, pixel_size_A: float, sigma_A: float, tilt_axis="y", smoothing_A: float = 0.5, tilt_axis_angle_deg: float = 0.0, device: str = "cpu", half_width_A: float = 10.0):
    """The smoothed Hann-filtered back-projection of one Gaussian atom of width ``sigma_A`` at
    the tilt centre, in the geometry of a tilt series of ``shape`` (N, H, W), scaled to 1 at its
    peak; returns it and the (3,) voxel index of the peak.  A point at the tilt centre projects
    to the centre pixel in every view, so its projections are one 2D Gaussian repeated.

    The detector is cut to ``half_width_A`` about its middle (so the series' own tilt centre
    does not enter): the response of a point is the same wherever it sits, and past
    10 Å (20 widths of a blurred atom) only the missing wedge's faint streaks remain, which
    :func:`clean_peaks` may ignore (it subtracts less, so keeps more).  The full 280-pixel Au
    detector took seconds of start-up; 81 pixels, a fraction of one."""
    volume = backprojected_atom(shape, angles_deg, pixel_size_A, sigma_A, tilt_axis, tilt_axis_angle_deg, device, half_width_A)
    return peak_normalised(ndimage.gaussian_filter(volume.data, smoothing_A / volume.spacing_A))


def peak_normalised(response: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``response`` scaled to 1 at its maximum, and the (3,) voxel index of that maximum."""
    centre = np.array(np.unravel_index(int(np.argmax(response)), response.shape))
    return response / response[tuple(centre)], centre


def clean_peaks(peaks: np.ndarray, values: np.ndarray, response: np.ndarray, centre: np.ndarray, level: float) -> tuple[np.ndarray, np.ndarray]:
    """Accept peaks strongest first, each judged on its value less the responses of those
    accepted before it.

    Parameters
    ----------
    peaks : (M, 3) int array, voxel indices, in the order to visit (strongest first)
    values : (M,) array, the volume's values there
    response : 3D array, one atom's response scaled to 1 at voxel ``centre`` (:func:`point_response`)
    centre : (3,) int array
    level : float, what a remaining value must exceed

    Returns
    -------
    accepted : (K,) int array, indices into ``peaks``
    amounts : (K,) array, their values after the subtraction
    """
    accepted = np.zeros(len(peaks), dtype=bool)
    amounts = np.zeros(len(peaks))
    shape = np.array(response.shape)
    if len(peaks) == 0:
        return np.zeros(0, dtype=np.int64), amounts
    # Only peaks within the response's box can take anything off one another: every such pair
    # (an earlier peak j, a later i) and its response weight from one k-d tree query, so the
    # visit itself is one short dot product per peak (10,438 Au candidates: 0.1 s, not 2.7 s).
    # (Chebyshev distance: exact on integer voxels, where the box's Euclidean half-diagonal
    # lost corner pairs to rounding.)
    reach = float(np.max(np.maximum(centre, shape - 1 - centre)))
    pairs = cKDTree(peaks).query_pairs(reach, p=np.inf, output_type="ndarray").reshape(-1, 2)
    later, earlier = pairs.max(axis=1), pairs.min(axis=1)
    offsets = peaks[later] - peaks[earlier] + centre
    inside = np.all((offsets >= 0) & (offsets < shape), axis=1)
    later, earlier, weights = later[inside], earlier[inside], response[tuple(offsets[inside].T)]
    order = np.argsort(later, kind="stable")
    earlier, weights = earlier[order], weights[order]
    bounds = np.searchsorted(later[order], np.arange(len(peaks) + 1))
    for i in range(len(peaks)):
        lo, hi = bounds[i], bounds[i + 1]
        value = float(values[i]) - (float(np.dot(amounts[earlier[lo:hi]], weights[lo:hi])) if hi > lo else 0.0)
        if value > level:  # amounts of peaks not accepted stay 0, so they take nothing off
            accepted[i], amounts[i] = True, value
    index = np.nonzero(accepted)[0]
    return index, amounts[index]
