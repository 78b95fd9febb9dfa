"""CLEAN-style peak acceptance and one atom's back-projected response (atoms/point_response.py)."""

import numpy as np
import pytest

from gaussian_atoms_method.atoms.point_response import (
    CLEAN_BLOCK,
    _response_pairs,
    clean_peaks,
    clean_peaks_reference,
    point_response,
    response_pairs_on_device,
)


def test_clean_drops_a_maximum_on_an_atoms_ridge_and_keeps_a_true_neighbour():
    """A response elongated along the last axis (the missing wedge: widths 2, 2, 5 voxels).  A
    maximum 6 voxels along the ridge of an atom of value 10 holds 10 exp(-36/50) = 4.87 of that
    atom plus 0.5 of its own: above the level 3, but 0.5 once the atom's response is taken off.
    A neighbour 6 voxels across the ridge keeps its own 10."""
    grid = np.indices((41, 41, 41)) - 20
    response = np.exp(-(grid[0] ** 2 / 8 + grid[1] ** 2 / 8 + grid[2] ** 2 / 50))
    centre = np.array([20, 20, 20])
    peaks = np.array([[30, 30, 30], [30, 36, 30], [30, 30, 36]])
    ridge = 10 * np.exp(-36 / 50) + 0.5
    values = np.array([10.0, 10.0 + 10 * np.exp(-36 / 8), ridge])
    accepted, amounts = clean_peaks(peaks, values, response, centre, level=3.0)
    assert accepted.tolist() == [0, 1]
    assert amounts == pytest.approx([10.0, 10.0])


def test_point_response_is_one_at_its_peak_and_the_cut_detector_changes_nothing_near_it():
    """The response from a detector cut to 10 Å about the centre equals, within 5 Å of the
    peak, the one from the whole 30 Å detector to 1e-3 (what the cut leaves out are the
    filter's far tails)."""
    angles = np.arange(-70.0, 71.0, 5.0)
    shape = (len(angles), 121, 121)
    full, c = point_response(shape, angles, 0.25, 0.5, half_width_A=1e9)
    cut, cc = point_response(shape, angles, 0.25, 0.5)
    assert full[tuple(c)] == pytest.approx(1.0) and cut[tuple(cc)] == pytest.approx(1.0)
    h = 20  # 5 Å
    a = full[c[0] - h : c[0] + h + 1, c[1] - h : c[1] + h + 1, c[2] - h : c[2] + h + 1]
    b = cut[cc[0] - h : cc[0] + h + 1, cc[1] - h : cc[1] + h + 1, cc[2] - h : cc[2] + h + 1]
    assert np.abs(a - b).max() < 1e-3


def _clean_by_definition(peaks, values, response, centre, level):
    """CLEAN as defined, with no pair search: each peak's value less every earlier accepted
    peak's amount times the response at their offset, where the offset lies in the box."""
    amounts = np.zeros(len(peaks))
    shape = np.array(response.shape)
    for i in range(len(peaks)):
        offsets = peaks[i] - peaks[:i] + centre
        inside = np.all((offsets >= 0) & (offsets < shape), axis=1) & (amounts[:i] != 0)
        value = values[i] - float(np.dot(amounts[:i][inside], response[tuple(offsets[inside].T)]))
        if value > np.broadcast_to(level, (len(peaks),))[i]:
            amounts[i] = value
    index = np.nonzero(amounts)[0]
    return index, amounts[index]


def test_clean_in_blocks_equals_clean_by_definition():
    """The blocked sparse visit and the per-peak reference accept the same peaks with the same
    amounts (to float64 rounding) as CLEAN written out pair by pair, at one level and at each
    peak's own: more peaks than a block,
    packed so that most lie in one another's box, a response with negative lobes and its peak
    off the box's middle (so some pairs within reach fall outside the box)."""
    rng = np.random.default_rng(5)
    grid = np.indices((15, 13, 17)).astype(float)
    centre = np.array([6, 7, 8])
    r2 = ((grid - centre[:, None, None, None]) ** 2 * np.array([1.0, 1.0, 0.3])[:, None, None, None]).sum(axis=0)
    response = np.exp(-r2 / 6) - 0.15 * np.exp(-r2 / 30)
    response /= response[tuple(centre)]
    peaks = np.unique(rng.integers(0, 40, (3 * CLEAN_BLOCK // 2, 3)), axis=0)
    peaks = peaks[rng.permutation(len(peaks))]
    values = np.sort(rng.uniform(0.5, 10.0, len(peaks)))[::-1]
    expected = _clean_by_definition(peaks, values, response, centre, 2.0)
    assert CLEAN_BLOCK < len(peaks) and 0.2 * len(peaks) < len(expected[0]) < len(peaks)
    for accepted, amounts in (
        clean_peaks(peaks, values, response, centre, 2.0),
        clean_peaks_reference(peaks, values, response, centre, 2.0),
    ):
        assert accepted.tolist() == expected[0].tolist()
        np.testing.assert_allclose(amounts, expected[1], rtol=1e-12)
    levels = rng.choice([2.0, 3.5], len(peaks))  # each peak its own level (the residual search's open places)
    expected = _clean_by_definition(peaks, values, response, centre, levels)
    for accepted, amounts in (
        clean_peaks(peaks, values, response, centre, levels),
        clean_peaks_reference(peaks, values, response, centre, levels),
    ):
        assert accepted.tolist() == expected[0].tolist()
        np.testing.assert_allclose(amounts, expected[1], rtol=1e-12)


def test_pairs_found_on_a_device_are_the_k_d_trees():
    """The binned search (torch, run here on the CPU) lists exactly the k-d tree's pairs within
    the response's reach, with the same weights: peaks packed so that most pairs lie within
    reach, some beyond the box on its short side (the peak off the box's middle), in chunks
    smaller than one peak's candidates and in one."""
    rng = np.random.default_rng(7)
    response = rng.uniform(-0.2, 1.0, (9, 11, 7))
    centre = np.array([3, 6, 2])
    peaks = np.unique(rng.integers(0, 30, (2000, 3)), axis=0)
    peaks = peaks[rng.permutation(len(peaks))]
    later, earlier, weights = _response_pairs(peaks, response, centre)
    order = np.lexsort((earlier, later))
    for chunk in (50, 1 << 26):
        got = response_pairs_on_device(peaks, response, centre, "cpu", max_candidates=chunk)
        assert len(later) > 10 * len(peaks)
        np.testing.assert_array_equal(got[0], later[order])
        np.testing.assert_array_equal(got[1], earlier[order])
        np.testing.assert_array_equal(got[2], weights[order])
    for few in (peaks[:0], peaks[:1]):  # no pair to find
        assert all(len(x) == 0 for x in response_pairs_on_device(few, response, centre, "cpu"))
