"""The population's prior on widths and masses in the stated precision (atoms/population.py)."""

import numpy as np
import pytest

from gaussian_atoms_method.atoms.evidence import atom_evidence
from gaussian_atoms_method.atoms.information import pair_information
from gaussian_atoms_method.atoms.population import population_precision, population_spread
from gaussian_atoms_method.physics.geometry import detector_axes_from_tilts

PIXEL_A, NOISE = 0.2, 0.03
AXES = detector_axes_from_tilts(np.linspace(-60, 60, 9))
SIGMA_A, PEAK = 0.5, 1.3


def _evidence(positions_A, spread=None):
    n = len(positions_A)
    sigmas, peaks = np.full(n, SIGMA_A), np.full(n, PEAK)
    population = None if spread is None else population_precision(sigmas, peaks, spread)
    return atom_evidence(positions_A, sigmas, peaks, AXES, PIXEL_A, NOISE, population=population)


def _positions_only_std(positions_A):
    """The first atom's x, y, z standard deviations from the information of every atom's
    position alone (widths and masses held), float64."""
    n = len(positions_A)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    i, j = i.ravel(), j.ravel()
    widths, peaks = np.full(n * n, SIGMA_A), np.full(n * n, PEAK)
    blocks = pair_information(positions_A[i], positions_A[j], widths, widths, peaks, peaks, AXES, PIXEL_A)
    info = blocks.reshape(n, n, 5, 5)[:, :, :3, :3].transpose(0, 2, 1, 3).reshape(3 * n, 3 * n) / NOISE**2
    return np.sqrt(np.diag(np.linalg.inv(info))[:3])


def test_a_population_that_holds_the_widths_and_masses_gives_a_bonded_pairs_positions_only_precision():
    """Two atoms 1.45 Å apart (a carbon bond; 0.5 Å wide, nearly three widths): with widths and
    masses free each position is known less well than with them held (the neighbour's width and
    mass take up part of a move); a population a millionth wide holds them, and the stated
    precision is then the positions' alone (to 1e-4); a population as wide as the information
    itself gives a precision between the two."""
    pair = np.array([[0.0, 0.0, 0.0], [0.9, 0.5, 1.0]])
    pair[1] *= 1.45 / np.linalg.norm(pair[1])
    free = _evidence(pair).position_std_A[0]
    held = _positions_only_std(pair)
    assert np.all(free > 1.05 * held)  # the freedom the population takes away matters here
    tight = _evidence(pair, np.diag([1e-6, 1e-6]) ** 2).position_std_A[0]
    np.testing.assert_allclose(tight, held, rtol=1e-4)
    between = _evidence(pair, np.diag([0.1, 0.3]) ** 2).position_std_A[0]
    assert np.all(between < free) and np.all(between > held)


def test_an_isolated_atoms_precision_and_every_atoms_significance_ignore_the_population():
    """Alone, an atom's position does not couple to its width and mass (its image is symmetric
    about it), so the population changes nothing (1e-9); the significance asks what the
    neighbours could take up with every parameter free, and stays as it was exactly."""
    alone = np.zeros((1, 3))
    spread = np.diag([0.05, 0.2]) ** 2
    np.testing.assert_allclose(_evidence(alone, spread).position_std_A, _evidence(alone).position_std_A, rtol=1e-9)
    pair = np.array([[0.0, 0.0, 0.0], [1.45, 0.0, 0.0]])
    np.testing.assert_array_equal(_evidence(pair, spread).significance, _evidence(pair).significance)


@pytest.mark.parametrize("outliers", [0, 50])
def test_the_populations_spread_is_robust_to_a_few_gaussians_far_from_it(outliers):
    """2,000 widths 5% and masses 15% about their medians read back their spread within 8% (three
    standard errors of a median absolute deviation over 2,000 draws, 37% efficient: 2.6% each),
    with 50 noise Gaussians ten times wider and a hundredth as high among them or not."""
    rng = np.random.default_rng(3)
    log_sigma = rng.normal(np.log(0.6), 0.05, 2000)
    log_q = rng.normal(0.0, 0.15, 2000) - 3 * (log_sigma - np.log(0.6))
    sigmas = np.r_[np.exp(log_sigma), np.full(outliers, 6.0)]
    peaks = np.r_[np.exp(log_q), np.full(outliers, 0.01)]
    spread = population_spread(sigmas, peaks)
    expected = [0.05, np.hypot(0.15, 3 * 0.05)]
    np.testing.assert_allclose(np.sqrt(np.diag(spread)), expected, rtol=0.08)
