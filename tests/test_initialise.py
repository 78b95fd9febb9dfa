"""Starting positions from the smoothed back-projection."""

import numpy as np
from scipy.spatial import cKDTree

from gaussian_atoms_method.initialise import backprojection_candidates
from gaussian_atoms_method.simulate import parse_tilts, simulate_gaussian_tilt_series, spherical_particle


def test_candidates_cover_every_atom():
    """Limited tilts, noisy Gaussian-potential Au sphere: every atom has a candidate within
    0.75 Å (the scoring radius; a candidate is a voxel maximum, so within half a voxel diagonal
    of the peak plus the missing wedge's elongation), candidates are more than min_distance_A
    apart, strongest first, and never more than asked for."""
    atoms = spherical_particle("Au", radius_A=8.0)
    angles = parse_tilts("limited")
    sim = simulate_gaussian_tilt_series(atoms, angles, noise_std=20.0, seed=1)
    n_max = 3 * len(atoms)
    cand = backprojection_candidates(sim.projections, sim.angles_deg, sim.pixel_size_A, max_count=n_max)
    assert 0 < len(cand) <= n_max
    dist, _ = cKDTree(cand).query(atoms.positions)
    assert np.all(dist < 0.75), f"{np.sum(dist >= 0.75)} of {len(atoms)} atoms have no candidate"
    pair_dist, _ = cKDTree(cand).query(cand, k=2)
    assert pair_dist[:, 1].min() > 1.5
    # The first len(atoms) candidates are the atoms themselves: the strongest maxima.
    first, _ = cKDTree(atoms.positions).query(cand[: len(atoms)])
    assert np.mean(first < 0.75) > 0.98

    few = backprojection_candidates(sim.projections, sim.angles_deg, sim.pixel_size_A, max_count=10)
    np.testing.assert_allclose(few, cand[:10])
    assert len(backprojection_candidates(sim.projections, sim.angles_deg, sim.pixel_size_A, max_count=0)) == 0
