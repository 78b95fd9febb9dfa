"""The precision calibrated against actual errors (atoms/calibration.py): the floor a replica reads
and the statement it widens; float64 references, tolerances from the estimator's own scatter."""

import numpy as np
import pytest

from gaussian_atoms_method.atoms.calibration import Z95, precision_floor_A, with_floor
from gaussian_atoms_method.engine.errors import OptionError
from gaussian_atoms_method.engine.options import FitOptions


def _errors(n=40_000, floor=(0.03, 0.0, 0.08), seed=0):
    """Errors of atoms whose stated precision holds the views' scatter (1-6 pm, 3-12 pm along z)
    and misses a bias the same in every view of variance ``floor**2``."""
    rng = np.random.default_rng(seed)
    stated = rng.uniform(0.01, 0.06, size=(n, 3)) * np.array([1.0, 1.0, 2.0])
    error = rng.normal(size=(n, 3)) * np.sqrt(stated**2 + np.asarray(floor) ** 2)
    return error, stated


def test_the_floor_a_replica_reads_is_the_bias_its_statement_misses():
    """With 40,000 atoms the mean square's relative standard error is sqrt(2/n) of the errors'
    variance: 0.7%, so the floor's variance comes back to 3% of the errors' variance, and a
    statement that holds everything (floor 0) reads at most that."""
    error, stated = _errors()
    floor = precision_floor_A(error, stated)
    total = np.mean(error**2, axis=0)
    assert floor**2 == pytest.approx(np.array([0.03, 0.0, 0.08]) ** 2, abs=0.03 * total.max())
    assert floor[1] ** 2 <= 0.03 * total[1]
    assert precision_floor_A(np.zeros((0, 3)), np.zeros((0, 3))).tolist() == [0.0, 0.0, 0.0]


def test_the_floor_brings_the_intervals_to_95_percent_on_a_second_replica():
    """Read on one replica, given to a run of another (new noise, new bias): its 95% intervals
    hold 0.95 of the errors to the binomial scatter (0.1% at 40,000 atoms, 0.5% allowed), where
    the statement alone held far fewer along the axes with a floor."""
    error, stated = _errors(seed=1)
    floor = precision_floor_A(error, stated)
    error2, stated2 = _errors(seed=2)
    alone = np.mean(np.abs(error2) <= Z95 * stated2, axis=0)
    std, half, flag = with_floor(stated2, Z95 * stated2[:, 2], np.zeros(len(stated2), bool), floor, 1.6)
    held = np.mean(np.abs(error2) <= Z95 * std, axis=0)
    assert alone[0] < 0.85 and alone[2] < 0.80 and alone[1] == pytest.approx(0.95, abs=0.005)
    assert held == pytest.approx([0.95, 0.95, 0.95], abs=0.005)
    # the depth interval along z widens with it, and the flag rises where it passes half the core
    assert np.mean(np.abs(error2[:, 2]) <= half) == pytest.approx(0.95, abs=0.005)
    assert np.array_equal(flag, 2 * half > 0.8)


def test_a_floor_that_cannot_be_a_length_is_named():
    with pytest.raises(OptionError, match="precision-floor-A"):
        FitOptions(precision_floor_A=(0.01, -0.02, 0.0)).check()
    FitOptions(precision_floor_A=(0.01, 0.02, 0.05)).check()
