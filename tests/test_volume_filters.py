"""The start's filters and maxima in torch against scipy's and numpy's references (float64)."""

import numpy as np
import pytest
import torch
from scipy import ndimage
from scipy.spatial import cKDTree

from gaussian_atoms_method.atoms import maxima, volume_filters
from gaussian_atoms_method.atoms.point_response import clean_peaks


@pytest.mark.parametrize("sigma_vox", [0.8, 2.0, 3.5])
def test_gaussian_filter_and_laplace_equal_scipy(sigma_vox):
    """Same kernels and scipy's reflect boundary, also where the kernel is longer than an axis
    (sigma 3.5: radius 14 on a 9-voxel axis): equal to float64 rounding."""
    volume = np.random.default_rng(0).standard_normal((23, 9, 31))
    tensor = torch.from_numpy(volume)
    for ours, theirs in (
        (volume_filters.gaussian_filter, ndimage.gaussian_filter),
        (volume_filters.gaussian_laplace, ndimage.gaussian_laplace),
    ):
        expected = theirs(volume, sigma_vox)
        np.testing.assert_allclose(
            ours(tensor, sigma_vox, in_torch=True).numpy(), expected, rtol=0, atol=1e-12 * np.abs(expected).max()
        )
        np.testing.assert_array_equal(ours(tensor, sigma_vox).numpy(), expected)  # on the CPU: scipy's own passes
    for in_torch in (True, False):
        smooth, laplace = volume_filters.gaussian_filter_and_laplace(tensor, sigma_vox, in_torch)
        np.testing.assert_array_equal(
            smooth.numpy(), volume_filters.gaussian_filter(tensor, sigma_vox, in_torch).numpy()
        )
        np.testing.assert_array_equal(
            laplace.numpy(), volume_filters.gaussian_laplace(tensor, sigma_vox, in_torch).numpy()
        )


@pytest.mark.parametrize("shape", [(40, 37, 45), (3, 1, 50), (1, 60, 2)])
def test_host_passes_in_threads_are_scipys_bit_for_bit(shape):
    """scipy's 1-D filters over slabs in threads (two threads here, more slabs than some axes
    hold) give scipy's own values exactly, in float32 and float64: Gaussian, its Laplacian, and
    the 3 x 3 x 3 maximum."""
    from gaussian_atoms_method.atoms import host_filters

    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        for dtype in (np.float32, np.float64):
            volume = np.random.default_rng(2).standard_normal(shape).astype(dtype)
            tensor = torch.from_numpy(volume)
            np.testing.assert_array_equal(
                volume_filters.gaussian_filter(tensor, 1.3).numpy(), ndimage.gaussian_filter(volume, 1.3)
            )
            np.testing.assert_array_equal(
                volume_filters.gaussian_laplace(tensor, 1.3).numpy(), ndimage.gaussian_laplace(volume, 1.3)
            )
            np.testing.assert_array_equal(
                host_filters.maximum_filter3(volume), ndimage.maximum_filter(volume, size=3, mode="nearest")
            )
    finally:
        torch.set_num_threads(threads)


def test_pooled_maxima_equal_the_numpy_search():
    """The maximum-pool search (what a GPU runs) finds the voxels the numpy search finds, at a
    level and without one, and the strongest-first suppression keeps the same ones."""
    field = ndimage.gaussian_filter(np.random.default_rng(1).standard_normal((30, 26, 28)), 1.5)
    tensor = torch.from_numpy(field)
    for level in (0.0, 0.05):
        expected = maxima.local_maxima_host(field, level)
        np.testing.assert_array_equal(maxima.local_maxima_device(tensor, level, pooled=True), expected)
        np.testing.assert_array_equal(maxima.local_maxima_device(tensor, level), expected)
    np.testing.assert_array_equal(
        maxima.separated_maxima_device(tensor, 0.25, 1.0, 0.02), maxima.separated_maxima_host(field, 0.25, 1.0, 0.02)
    )


def test_suppression_on_a_device_keeps_what_the_greedy_visit_keeps():
    """The suppression in rounds (torch, run here on the CPU) keeps the points the host's
    strongest-first visit keeps, in its order: points packed at a few voxels' spacing, values
    with ties, at a dyadic and a non-dyadic spacing, a distance a whole number of voxels
    (pairs exactly at it suppress) and one between."""
    rng = np.random.default_rng(4)
    points = np.unique(rng.integers(0, 40, (4000, 3)), axis=0)
    values = np.round(rng.uniform(0, 5, len(points)), 1)  # many ties
    for spacing_A, min_distance_A in ((0.25, 1.0), (0.25, 0.7), (0.32, 1.0)):
        expected = maxima.suppress_within_host(points * spacing_A, np.argsort(-values, kind="stable"), min_distance_A)
        got = maxima.suppress_within_device(torch.as_tensor(points), values, spacing_A, min_distance_A)
        assert 20 < len(expected) < len(points) // 2
        np.testing.assert_array_equal(got, expected)
    one, none = torch.zeros((1, 3), dtype=torch.long), torch.zeros((0, 3), dtype=torch.long)
    assert maxima.suppress_within_device(one, np.ones(1), 0.25, 1.0).tolist() == [0]
    assert maxima.suppress_within_device(none, np.zeros(0), 0.25, 1.0).tolist() == []


def _clean_reference(found, values, response, centre, level):
    """CLEAN as a plain loop: each peak less every accepted earlier peak's response there."""
    accepted, amounts = [], []
    for i in range(len(found)):
        value = values[i]
        for j, amount in zip(accepted, amounts):
            offset = found[i] - found[j] + centre
            if np.all(offset >= 0) and np.all(offset < response.shape):
                value -= amount * response[tuple(offset)]
        if value > level:
            accepted.append(i)
            amounts.append(value)
    return np.array(accepted, dtype=np.int64), np.array(amounts)


def test_clean_peaks_equals_the_plain_loop():
    rng = np.random.default_rng(2)
    found = rng.integers(0, 40, (300, 3))
    found = found[np.unique(found, axis=0, return_index=True)[1]]
    values = np.sort(rng.uniform(0.5, 2.0, len(found)))[::-1]
    grid = np.indices((9, 9, 9)) - 4
    response = np.exp(-(grid**2).sum(axis=0) / 8.0)
    centre = np.array([4, 4, 4])
    index, amounts = clean_peaks(found, values, response, centre, 0.6)
    expected_index, expected_amounts = _clean_reference(found, values, response, centre, 0.6)
    assert 0 < len(expected_index) < len(found)  # some are taken off by a neighbour
    np.testing.assert_array_equal(index, expected_index)
    np.testing.assert_allclose(amounts, expected_amounts, rtol=1e-12)
    assert len(cKDTree(found).query_pairs(4 * np.sqrt(3))) > 0  # neighbours within reach exist
