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
    """With 40,000 atoms the coverage at the true floor scatters by sqrt(0.95 x 0.05 / n) = 0.1%;
    a floor 10% off moves it by 0.5-1.5% here, so the floor comes back to 10%; a statement that
    holds everything (no floor along y) reads a floor far under its 1-6 pm.  An open atom's
    wide interval does not hide the others' miss (a mean square would)."""
    error, stated = _errors()
    floor = precision_floor_A(error, stated)
    assert floor[[0, 2]] == pytest.approx([0.03, 0.08], rel=0.1) and floor[1] < 0.005
    wide = stated.copy()
    wide[:100] = 10.0  # one atom in 400 left open, stated to 10 Å
    assert precision_floor_A(error, wide)[[0, 2]] == pytest.approx([0.03, 0.08], rel=0.1)
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


def test_with_the_floor_another_place_opens_where_the_widened_interval_reaches_it():
    """For a cost quadratic along the beam, the rise at a distance ``d`` is ``(d / sigma)^2`` noise
    variances; with a floor ``f`` the error's variance is ``sigma^2 + f^2``, so the place lies in
    the 95% interval exactly where ``d < 1.96 sqrt(sigma^2 + f^2)``, the widened half-width.
    The flag from the rise alone must agree with that interval for every atom (float64, exact
    but for atoms on the boundary)."""
    rng = np.random.default_rng(3)
    n = 20_000
    sigma = rng.uniform(0.01, 0.06, n)
    d = rng.uniform(0.0, 0.5, n)
    floor = (0.0, 0.0, 0.08)
    stated = np.zeros((n, 3)) + sigma[:, None]
    std, half, flag = with_floor(stated, Z95 * sigma, np.zeros(n, bool), floor, None, (d / sigma) ** 2)
    assert np.array_equal(flag, d < half)
    assert 0.05 < flag.mean() < 0.95  # both sides are exercised
    # without the rise, or with none known, nothing but the width opens an atom
    assert not with_floor(stated, Z95 * sigma, np.zeros(n, bool), floor, None)[2].any()
    assert not with_floor(stated, Z95 * sigma, np.zeros(n, bool), floor, None, np.full(n, np.nan))[2].any()


def test_a_floor_that_cannot_be_a_length_is_named():
    with pytest.raises(OptionError, match="precision-floor-A"):
        FitOptions(precision_floor_A=(0.01, -0.02, 0.0)).check()
    FitOptions(precision_floor_A=(0.01, 0.02, 0.05)).check()


def test_a_floor_given_as_numpy_numbers_is_written_as_numbers():
    """A floor read by ``precision_floor_A`` is a numpy array; handed on as ``tuple(floor)`` its
    items are ``np.float64``, and the run's config.yml (safe YAML) takes them as plain floats."""
    import dataclasses

    import yaml

    from gaussian_atoms_method.engine.run_files import options_dict, plain

    floor = tuple(precision_floor_A(*_errors(n=2_000)))
    written = options_dict(dataclasses.replace(FitOptions(), precision_floor_A=floor))["precision_floor_A"]
    assert all(type(f) is float for f in written) and written == [float(f) for f in floor]
    assert yaml.safe_load(yaml.safe_dump(plain({"floor": floor}))) == {"floor": written}
