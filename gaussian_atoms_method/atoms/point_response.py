"""What one atom looks like in a smoothed back-projection, and peaks taken CLEAN-style.

A limited tilt range and the filter make one atom's filtered back-projection elongated along
the missing wedge, with side lobes; on that ridge noise makes more than one local maximum, and a
list of maxima then holds one atom several times.  So maxima are accepted strongest first, as in
Högbom's CLEAN: each accepted one's response (:func:`point_response`, scaled to its value) is
taken off the values of those not yet visited, which must still clear the level.  A true
neighbour keeps its own peak after the subtraction; a maximum made of the first atom's ridge
does not.  Used by the start (:mod:`.candidates`) and the search of the residuals
(:mod:`.residual_sites`).
"""

from __future__ import annotations

import numpy as np
import scipy
import torch
from scipy import sparse
from scipy.spatial import cKDTree

from gaussian_atoms_method.atoms.voxel_pairs import pairs_within
from gaussian_atoms_method.physics.reconstruction import reconstruct


def backprojected_atom(
    shape,
    angles_deg,
    pixel_size_A: float,
    sigma_A: float,
    tilt_axis="y",
    tilt_axis_angle_deg: float = 0.0,
    device: str = "cpu",
    half_width_A: float = 10.0,
):
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
    return reconstruct(
        np.repeat(image[None], n, axis=0),
        angles_deg,
        pixel_size_A,
        "fbp",
        tilt_axis,
        None,
        filter_name="hann",
        device=device,
        tilt_axis_angle_deg=tilt_axis_angle_deg,
    )


def point_response(
    shape,
    angles_deg,
    pixel_size_A: float,
    sigma_A: float,
    tilt_axis="y",
    smoothing_A: float = 0.5,
    tilt_axis_angle_deg: float = 0.0,
    device: str = "cpu",
    half_width_A: float = 10.0,
):
    """The smoothed Hann-filtered back-projection of one Gaussian atom of width ``sigma_A`` at
    the tilt centre, in the geometry of a tilt series of ``shape`` (N, H, W), scaled to 1 at its
    peak; returns it and the (3,) voxel index of the peak.  A point at the tilt centre projects
    to the centre pixel in every view, so its projections are one 2D Gaussian repeated.

    The detector is cut to ``half_width_A`` about its middle (so the series' own tilt centre
    does not enter): the response of a point is the same wherever it sits, and past
    10 Å (20 widths of a blurred atom) only the missing wedge's faint streaks remain, which
    :func:`clean_peaks` may ignore (it subtracts less, so keeps more).  The full 280-pixel Au
    detector took seconds of start-up; 81 pixels, a fraction of one."""
    volume = backprojected_atom(
        shape, angles_deg, pixel_size_A, sigma_A, tilt_axis, tilt_axis_angle_deg, device, half_width_A
    )
    return peak_normalised(scipy.ndimage.gaussian_filter(volume.data, smoothing_A / volume.spacing_A))


def peak_normalised(response: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``response`` scaled to 1 at its maximum, and the (3,) voxel index of that maximum."""
    centre = np.array(np.unravel_index(int(np.argmax(response)), response.shape))
    return response / response[tuple(centre)], centre


def clean_peaks(
    peaks: np.ndarray, values: np.ndarray, response: np.ndarray, centre: np.ndarray, level: float, device=None
) -> tuple[np.ndarray, np.ndarray]:
    """Accept peaks strongest first, each judged on its value less the responses of those
    accepted before it.

    Parameters
    ----------
    peaks : (M, 3) int array, voxel indices, in the order to visit (strongest first)
    values : (M,) array, the volume's values there
    response : 3D array, one atom's response scaled to 1 at voxel ``centre`` (:func:`point_response`)
    centre : (3,) int array
    level : float or (M,) array, what a remaining value must exceed (each peak's own)
    device : torch device, optional
        Off the CPU, the pairs within the response's box are found there
        (:func:`response_pairs_on_device`); the visit stays on the host.  The same result.

    Returns
    -------
    accepted : (K,) int array, indices into ``peaks``
    amounts : (K,) array, their values after the subtraction
    """
    if len(peaks) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0)
    on_device = device is not None and torch.device(device).type != "cpu"
    later, earlier, weights = (
        response_pairs_on_device(peaks, response, centre, device)
        if on_device
        else _response_pairs(peaks, response, centre)
    )
    # Row i of W holds the weights of the peaks visited before i.  In blocks of the visit order:
    # what the earlier blocks' accepted peaks take off is one sparse product (amounts of peaks
    # not yet visited are still 0), and only the pairs inside a block are visited one by one,
    # in plain Python (77k a-Pd candidates, 15 million pairs: the visit took about 1 s less than
    # the per-peak numpy of :func:`clean_peaks_reference`; finding the pairs is the rest).
    n = len(peaks)
    W = sparse.csr_matrix((weights, (later, earlier)), shape=(n, n))
    amounts = np.zeros(n)
    levels = np.broadcast_to(np.asarray(level, dtype=np.float64), (n,)).tolist()
    for start in range(0, n, CLEAN_BLOCK):
        stop = min(start + CLEAN_BLOCK, n)
        rows = W[start:stop]
        remaining = (np.asarray(values[start:stop], dtype=np.float64) - rows @ amounts).tolist()
        inside = rows[:, start:stop].tocsr()
        indptr, columns, w = inside.indptr.tolist(), inside.indices.tolist(), inside.data.tolist()
        block = [0.0] * (stop - start)
        for r in range(stop - start):
            value = remaining[r]
            for t in range(indptr[r], indptr[r + 1]):
                value -= block[columns[t]] * w[t]
            if value > levels[start + r]:  # amounts of peaks not accepted stay 0, so they take nothing off
                block[r] = value
        amounts[start:stop] = block
    index = np.nonzero(amounts)[0]
    return index, amounts[index]


CLEAN_BLOCK = 1024
"""Peaks per block of :func:`clean_peaks`' visit (a cost trade-off only: the result is the same)."""


def _response_pairs(peaks: np.ndarray, response: np.ndarray, centre: np.ndarray):
    """Every pair of (M, 3) voxel ``peaks`` within the response's box: the later one's index,
    the earlier one's, and the earlier one's response weight at the later one.  Only such
    pairs can take anything off one another; Chebyshev distance is exact on integer voxels,
    where the box's Euclidean half-diagonal lost corner pairs to rounding."""
    shape = np.array(response.shape)
    reach = float(np.max(np.maximum(centre, shape - 1 - centre)))
    pairs = cKDTree(peaks).query_pairs(reach, p=np.inf, output_type="ndarray").reshape(-1, 2)
    earlier, later = pairs[:, 0], pairs[:, 1]  # query_pairs gives i < j
    # The offset's flat index into the response, one axis at a time in int32 (15 million a-Pd
    # pairs: 1.3 s, against 3.4 s for (K, 3) int64 offsets).
    flat, inside, stride = np.zeros(len(pairs), dtype=np.int64), np.ones(len(pairs), dtype=bool), 1
    for axis in (2, 1, 0):
        coordinate = np.ascontiguousarray(peaks[:, axis], dtype=np.int32)
        offset = coordinate[later]
        offset -= coordinate[earlier]
        offset += int(centre[axis])
        inside &= (offset >= 0) & (offset < shape[axis])
        flat += offset * stride
        stride *= int(shape[axis])
    return later[inside], earlier[inside], np.take(response.ravel(), flat[inside])


def response_pairs_on_device(
    peaks: np.ndarray, response: np.ndarray, centre: np.ndarray, device, max_candidates: int = 1 << 26
):
    """:func:`_response_pairs` found on ``device`` in torch (:func:`.voxel_pairs.pairs_within`),
    sorted by (later, earlier): the same pairs and weights, without the host's k-d tree search
    (millions of pairs at tens of thousands of atoms)."""
    shape = np.array(response.shape)
    reach = int(np.max(np.maximum(centre, shape - 1 - centre)))
    dev = torch.device(device)
    points = torch.as_tensor(np.asarray(peaks, dtype=np.int64).reshape(-1, 3), device=dev)
    response_t = torch.as_tensor(response, device=dev).reshape(-1)
    box, centre_t = torch.as_tensor(shape, device=dev), torch.as_tensor(np.asarray(centre), device=dev)
    found = []
    for earlier, later in pairs_within(points, reach, max_candidates):
        offset = points[later] - points[earlier] + centre_t
        inside = ((offset >= 0) & (offset < box)).all(dim=1)
        earlier, later, offset = earlier[inside], later[inside], offset[inside]
        found.append((later, earlier, response_t[(offset[:, 0] * box[1] + offset[:, 1]) * box[2] + offset[:, 2]]))
    if not found:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0)
    later, earlier, weights = (torch.cat(parts) for parts in zip(*found))
    pair_order = torch.argsort(later * len(points) + earlier)
    return tuple(x[pair_order].cpu().numpy() for x in (later, earlier, weights))


def clean_peaks_reference(
    peaks: np.ndarray, values: np.ndarray, response: np.ndarray, centre: np.ndarray, level: float
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`clean_peaks` one peak at a time in numpy (the tests' reference)."""
    amounts = np.zeros(len(peaks))
    if len(peaks) == 0:
        return np.zeros(0, dtype=np.int64), amounts
    later, earlier, weights = _response_pairs(peaks, response, centre)
    order = np.argsort(later, kind="stable")
    earlier, weights = earlier[order], weights[order]
    bounds = np.searchsorted(later[order], np.arange(len(peaks) + 1))
    levels = np.broadcast_to(np.asarray(level, dtype=np.float64), (len(peaks),))
    for i in range(len(peaks)):
        lo, hi = bounds[i], bounds[i + 1]
        value = float(values[i]) - (float(np.dot(amounts[earlier[lo:hi]], weights[lo:hi])) if hi > lo else 0.0)
        if value > levels[i]:
            amounts[i] = value
    index = np.nonzero(amounts)[0]
    return index, amounts[index]
