"""The run's own replica read on a slab across the tilt axis (engine/own_floor.py)."""

import numpy as np

import gaussian_atoms_method as ga
from dataparsers.tilt_series_format import TiltSeries
from gaussian_atoms_method.engine import own_floor
from gaussian_atoms_method.harness.simulate import parse_tilts, simulate_gaussian_tilt_series, spherical_particle


def test_a_floor_read_on_a_slab_changes_what_is_stated_and_nothing_else(monkeypatch):
    """A small Au sphere whose run holds more atoms than the floor is read on (the number
    lowered here from 2,000 to 30): the replica draws and refits the slab across the tilt axis
    that holds 30 of them and its neighbour search's reach either side, reads its floor on those
    30, and puts the model back whole.  The atoms, their proofs and the statements before the
    floor are then those of the run without a floor, and every statement is widened by the
    floor read (finite, under the 5 pm a refit of a Gaussian replica could move 30 atoms)."""
    truth = spherical_particle("Au", radius_A=10.0)
    sim = simulate_gaussian_tilt_series(truth, parse_tilts("limited"), noise_std=20.0, seed=1)
    series = TiltSeries(sim.projections, sim.angles_deg, sim.pixel_size_A)
    monkeypatch.setattr(own_floor, "FLOOR_ATOMS", 30)
    atoms = ga.reconstruct(series, device="cpu", progress=False)
    assert len(atoms) > 2 * 30 and atoms.info["precision_floor_atoms"] == 30
    floor = np.asarray(atoms.info["precision_floor_A"])
    assert floor.shape == (3,) and np.all(np.isfinite(floor)) and np.all(floor < 0.05)
    plain = ga.reconstruct(series, device="cpu", progress=False, own_floor=False)
    np.testing.assert_array_equal(atoms.positions, plain.positions)
    np.testing.assert_array_equal(atoms.proven, plain.proven)
    np.testing.assert_allclose(atoms.position_std_A, np.sqrt(plain.position_std_A**2 + floor**2), rtol=1e-12)
