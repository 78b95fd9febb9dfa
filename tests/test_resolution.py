"""The merge test's chi-square (atoms/resolution.py) against a float64 pixel reference."""

import numpy as np
import pytest

from gaussian_atoms_method.atoms.resolution import SEARCH_WIDTHS, candidate_pairs, merge_energy, merged_moments


def _project(positions, sigmas, masses, direction, grid):
    """Render isotropic 3D Gaussians of the given masses along ``direction`` onto an (x, y)
    grid in the plane perpendicular to it: the plain reference."""
    u = direction / np.linalg.norm(direction)
    e1 = np.cross(u, [0.0, 1.0, 0.0] if abs(u[1]) < 0.9 else [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    x, y = grid
    image = np.zeros_like(x)
    for p, s, m in zip(positions, sigmas, masses):
        px, py = p @ e1, p @ e2
        image += m * np.exp(-((x - px) ** 2 + (y - py) ** 2) / (2 * s**2)) / (2 * np.pi * s**2)
    return image


def test_merge_energy_equals_the_pixel_sum_of_the_rendered_change():
    """For a pair of unequal Gaussians and three views, the closed form (sum of products of
    normalised Gaussians) equals the squared change between the rendered pair and its merged
    Gaussian, summed over a 0.02 Å grid times the pixel area (Riemann sums of Gaussians at 20+
    samples per width are exact to ~1e-12; the grid spans 7 widths beyond every centre)."""
    positions = np.array([[0.1, -0.2, 0.3], [0.9, 0.4, -0.6]])
    sigmas, masses = np.array([0.45, 0.6]), np.array([2.0, 0.7])
    dirs = np.array([[0.0, 0.0, 1.0], [np.sin(1.0), 0.0, np.cos(1.0)], [0.3, 0.5, 0.8]])
    pairs = np.array([[0, 1]])
    centre, s_c = merged_moments(positions, sigmas, masses, pairs)
    step = 0.02
    axis = np.arange(-6.0, 6.0, step)
    grid = np.meshgrid(axis, axis, indexing="ij")
    reference = 0.0
    for u in dirs:
        pair = _project(positions, sigmas, masses, u, grid)
        merged = _project(centre, s_c, [masses.sum()], u, grid)
        reference += ((pair - merged) ** 2).sum() * step**2
    assert merge_energy(positions, sigmas, masses, pairs, dirs)[0] == pytest.approx(reference, rel=1e-9)


def test_merged_moments_keep_mass_centre_and_second_moment():
    positions = np.array([[0.0, 0.0, 0.0], [1.2, 0.0, 0.0]])
    sigmas, masses = np.array([0.4, 0.5]), np.array([3.0, 1.0])
    centre, s_c = merged_moments(positions, sigmas, masses, np.array([[0, 1]]))
    assert centre[0] == pytest.approx([0.3, 0.0, 0.0])
    second = (3.0 * (3 * 0.4**2 + 0.3**2) + 1.0 * (3 * 0.5**2 + 0.9**2)) / 4.0  # E|x - c|^2
    assert 3 * s_c[0] ** 2 == pytest.approx(second)


def test_candidate_pairs_within_three_combined_widths():
    positions = np.array([[0.0, 0.0, 0.0], [1.5, 0.0, 0.0], [5.0, 0.0, 0.0]])
    sigmas = np.array([0.4, 0.4, 2.0])  # 0-1: 1.5 < 3 * 0.566; 1-2: 3.5 < 3 * 2.04; 0-2: 5 < 6.1
    assert sorted(map(tuple, candidate_pairs(positions, sigmas).tolist())) == [(0, 1), (0, 2), (1, 2)]
    sigmas = np.array([0.4, 0.4, 0.4])
    assert candidate_pairs(positions, sigmas).tolist() == [[0, 1]]


def test_merge_energy_in_chunks_equals_all_at_once():
    rng = np.random.default_rng(0)
    positions, sigmas, masses = rng.normal(size=(40, 3)), rng.uniform(0.3, 0.7, 40), rng.uniform(0.5, 2.0, 40)
    pairs = np.array([(i, j) for i in range(40) for j in range(i + 1, 40)])
    dirs = rng.normal(size=(9, 3))
    whole = merge_energy(positions, sigmas, masses, pairs, dirs, chunk=len(pairs))
    assert np.array_equal(merge_energy(positions, sigmas, masses, pairs, dirs, chunk=100), whole)


def test_candidate_pairs_with_a_few_wide_gaussians_are_every_pair_within_reach():
    """A dense set of atom-wide Gaussians and 3% up to three times wider (the search splits
    them off): the same pairs as testing every pair, each once with i < j."""
    rng = np.random.default_rng(3)
    positions = rng.uniform(0.0, 12.0, (600, 3))
    sigmas = rng.uniform(0.55, 0.7, 600)
    wide = rng.random(600) < 0.03
    sigmas[wide] = rng.uniform(1.0, 2.0, wide.sum())
    i, j = np.triu_indices(600, k=1)
    within = np.linalg.norm(positions[i] - positions[j], axis=1) <= SEARCH_WIDTHS * np.hypot(sigmas[i], sigmas[j])
    pairs = candidate_pairs(positions, sigmas)
    assert (pairs[:, 0] < pairs[:, 1]).all()
    assert sorted(map(tuple, pairs.tolist())) == list(zip(i[within].tolist(), j[within].tolist()))
