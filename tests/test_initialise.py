"""Starting positions from the smoothed back-projection."""

import numpy as np
from scipy.spatial import cKDTree

from gaussian_atoms_method.atoms.candidates import backprojection_candidates
from gaussian_atoms_method.harness.simulate import parse_tilts, simulate_gaussian_tilt_series, spherical_particle


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
    assert pair_dist[:, 1].min() > 1.0  # min_distance_A: closer than any bond (C-C 1.42 Å)
    # The first len(atoms) candidates are the atoms themselves: the strongest maxima.
    first, _ = cKDTree(atoms.positions).query(cand[: len(atoms)])
    assert np.mean(first < 0.75) > 0.98

    # The smoothed back-projection at each candidate, strongest first: at a peak-to-noise of
    # about 20 an atom reads several times what a maximum made of noise does.
    same, values = backprojection_candidates(
        sim.projections, sim.angles_deg, sim.pixel_size_A, max_count=n_max, return_values=True
    )
    np.testing.assert_array_equal(same, cand)
    assert values.shape == (len(cand),) and np.all(np.diff(values) <= 0)
    on_atom = cKDTree(atoms.positions).query(cand)[0] < 0.75
    assert np.median(values[on_atom]) > 3 * np.median(values[~on_atom])

    few = backprojection_candidates(sim.projections, sim.angles_deg, sim.pixel_size_A, max_count=10)
    np.testing.assert_allclose(few, cand[:10])
    assert len(backprojection_candidates(sim.projections, sim.angles_deg, sim.pixel_size_A, max_count=0)) == 0


def test_shoulder_candidates_find_light_atoms_beside_heavy_ones():
    """Ni/Pd/Pt high-entropy alloy (Lobato potentials, limited tilts, noise 50): a Ni atom
    beside a Pt atom is often only a shoulder of the Pt atom's smoothed peak.  Smoothed peaks
    alone reach 85% of the Ni within the 0.75 Å scoring radius; the strong Laplacian maxima
    reach 95% (measured), adding a handful of candidates, not a flood, and keep the smoothed
    peaks first and unchanged."""
    from gaussian_atoms_method.harness.particles import make_particle
    from gaussian_atoms_method.harness.simulate import simulate_tilt_series

    atoms = make_particle("hea", 0.3, 0)
    sim = simulate_tilt_series(atoms, parse_tilts("limited"), "lobato", noise_std=50.0, seed=1)
    args = (sim.projections, sim.angles_deg, sim.pixel_size_A)
    peaks_only = backprojection_candidates(*args, max_count=3 * len(atoms), shoulders=False)
    filled = backprojection_candidates(*args, max_count=3 * len(atoms))
    np.testing.assert_allclose(filled[: len(peaks_only)], peaks_only)
    assert 0 < len(filled) - len(peaks_only) < 0.1 * len(atoms)

    def recall(cand, element):
        dist, _ = cKDTree(cand).query(atoms.positions[atoms.species == element])
        return np.mean(dist < 0.75)

    assert recall(peaks_only, "Ni") < 0.9
    assert recall(filled, "Ni") >= 0.93
    assert recall(filled, "Pd") == 1.0 and recall(filled, "Pt") == 1.0


def test_without_a_cap_the_count_follows_the_data():
    """No max_count: every maximum above the back-projected noise's family-wise level, so the
    count follows the data: every atom of the sphere has a candidate, fewer than twice as many
    candidates as atoms (the extra ones are the missing wedge's streaks), and pure noise of the
    same level gives almost none (at most one: the 5% false-alarm rate, three seeds)."""
    atoms = spherical_particle("Au", radius_A=8.0)
    angles = parse_tilts("limited")
    sim = simulate_gaussian_tilt_series(atoms, angles, noise_std=20.0, seed=1)
    cand = backprojection_candidates(sim.projections, sim.angles_deg, sim.pixel_size_A)
    assert np.all(cKDTree(cand).query(atoms.positions)[0] < 0.75)
    assert len(atoms) <= len(cand) < 2 * len(atoms)
    for seed in (1, 2, 3):
        noise = np.random.default_rng(seed).normal(0.0, 20.0, sim.projections.shape)
        assert len(backprojection_candidates(noise, sim.angles_deg, sim.pixel_size_A, shoulders=False)) <= 1


def test_fine_scale_candidates_resolve_bonded_carbon():
    """Disordered carbon (1.49 Å bonds, Lobato potentials, 0.32 Å pixels, tilts -72:4:72,
    noise 20): two bonded atoms are one peak of the 0.5 Å matched filter, and the 0.5 Å
    Laplacian's shoulders are within 1 Å of that peak.  Step 5 (the Laplacian at one voxel,
    cut at its own noise level, maxima half a bond apart) seats the neighbour: recall within
    0.75 Å 0.913 -> 0.978 on this 448-atom sphere (measured), for 35 more candidates; the
    earlier steps' candidates come first and unchanged."""
    from gaussian_atoms_method.harness.particles import make_particle
    from gaussian_atoms_method.harness.simulate import simulate_tilt_series

    atoms = make_particle("carbon", 0.4, 0)
    sim = simulate_tilt_series(atoms, parse_tilts("-72:4:72"), "lobato", noise_std=20.0, seed=1, pixel_size_A=0.32)
    args = (sim.projections, sim.angles_deg, sim.pixel_size_A)
    before = backprojection_candidates(*args, fine_scale_A=0)
    after = backprojection_candidates(*args, deconvolve=False)
    np.testing.assert_allclose(after[: len(before)], before)
    assert 0 < len(after) - len(before) < 0.1 * len(atoms)

    def recall(cand):
        return np.mean(cKDTree(cand).query(atoms.positions)[0] < 0.75)

    assert recall(before) < 0.93
    assert recall(after) >= 0.96
    assert cKDTree(after).query(after, k=2)[0][:, 1].min() > 0.7  # fine_min_distance_A apart


def test_deconvolution_seats_the_shoulder_atoms():
    """Step 6 on the same carbon sphere (noise 20): the candidates' fitted responses taken off
    the pixel-scale Laplacian leave the atoms that are a neighbour's shoulder at every scale.
    Measured: recall within 0.75 Å 0.978 -> 0.998 for 15 more candidates, 2 of them surplus
    (the decoy level allows a quarter).  Earlier candidates stay first and unchanged; the new
    ones lie more than half a bond from every other."""
    from gaussian_atoms_method.harness.particles import make_particle
    from gaussian_atoms_method.harness.simulate import simulate_tilt_series

    atoms = make_particle("carbon", 0.4, 0)
    sim = simulate_tilt_series(atoms, parse_tilts("-72:4:72"), "lobato", noise_std=20.0, seed=1, pixel_size_A=0.32)
    args = (sim.projections, sim.angles_deg, sim.pixel_size_A)
    before = backprojection_candidates(*args, deconvolve=False)
    after = backprojection_candidates(*args)
    np.testing.assert_allclose(after[: len(before)], before)
    added = after[len(before) :]
    assert 0 < len(added) < 0.1 * len(atoms)

    def recall(cand):
        return np.mean(cKDTree(cand).query(atoms.positions)[0] < 0.75)

    assert recall(after) >= recall(before) + 0.01 and recall(after) >= 0.99
    assert np.mean(cKDTree(atoms.positions).query(added)[0] < 0.75) >= 0.75  # the decoy level's share
    assert cKDTree(after).query(after, k=2)[0][:, 1].min() > 0.7


def test_a_given_start_is_taken_as_it_is():
    """``positions_A`` (``--pipeline.model.start-atoms``): the start is those positions in the
    model's units, with equal masses (no weights), whatever the data's candidates are."""
    import torch

    from gaussian_atoms_method.atoms.initialise import starting_positions

    given = np.array([[0.0, 1.0, -2.0], [3.5, 0.0, 0.25]])
    means, weights = starting_positions(None, 0.1, 50, 1.0, torch.Generator().manual_seed(0), positions_A=given)
    np.testing.assert_allclose(means.numpy(), 0.1 * given, rtol=1e-6)
    assert weights is None
