"""A missing atom is found from the residual (atoms/residual_sites.py), also a faint one where an
atom could be (atoms/holes.py)."""

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from gaussian_atoms_method.atoms.atom_set import AtomSet
from gaussian_atoms_method.atoms.residual_sites import unexplained_sites
from gaussian_atoms_method.harness.simulate import parse_tilts, simulate_gaussian_tilt_series, spherical_particle


def _missing_one(noise_std, seed=1):
    atoms = spherical_particle("Au", radius_A=6.0)
    angles = parse_tilts("limited")
    sim = simulate_gaussian_tilt_series(atoms, angles, noise_std=noise_std, seed=seed)
    missing = int(np.argmin(np.linalg.norm(atoms.positions - atoms.positions.mean(0), axis=1)))  # buried in the middle
    others = AtomSet(np.delete(atoms.positions, missing, axis=0), species=np.delete(np.asarray(atoms.species), missing))
    fitted = simulate_gaussian_tilt_series(others, angles, noise_std=0.0)
    assert fitted.projections.shape == sim.projections.shape
    return atoms, missing, others, sim, sim.projections - fitted.projections


def test_a_missing_atom_is_found_from_the_residual():
    """A fit holding every atom but one buried in the middle of a 6 Å Au sphere (limited tilts,
    peak-to-noise about 40): the residual's back-projection gives exactly one site, within
    0.5 Å of the missing atom (a voxel maximum of an FBP elongated by the missing wedge), with
    a mass within a factor two of one atom's (the limited range lowers the FBP's peak)."""
    atoms, missing, others, sim, residuals = _missing_one(noise_std=20.0)
    sites, masses = unexplained_sites(
        residuals, sim.angles_deg, sim.pixel_size_A, others.positions, sigma_A=float(sim.truth.sigmas[0])
    )
    assert len(sites) == 1
    assert np.linalg.norm(sites[0] - atoms.positions[missing]) < 0.5
    clean = simulate_gaussian_tilt_series(atoms, sim.angles_deg, noise_std=0.0).projections
    fitted = sim.projections - residuals
    atom_mass = float((clean - fitted).sum(axis=(1, 2)).mean()) * sim.pixel_size_A**2  # its projection's integral
    assert 0.5 * atom_mass < masses[0] < 2.0 * atom_mass


def test_a_complete_fit_leaves_no_site():
    """With every atom in the fit the residual is pure noise: no site anywhere (the threshold is
    the level no noise peak reaches in the volume at a 5% false-alarm rate; three noise seeds)."""
    atoms = spherical_particle("Au", radius_A=6.0)
    angles = parse_tilts("limited")
    clean = simulate_gaussian_tilt_series(atoms, angles, noise_std=0.0)
    for seed in (1, 2, 3):
        noisy = simulate_gaussian_tilt_series(atoms, angles, noise_std=20.0, seed=seed)
        sites, _ = unexplained_sites(
            noisy.projections - clean.projections, noisy.angles_deg, noisy.pixel_size_A, atoms.positions, sigma_A=0.6
        )
        assert len(sites) == 0


def test_sites_keep_clear_of_existing_gaussians():
    """A site closer than 1 Å to an existing Gaussian is not proposed (the Gaussian there takes
    up the mass); at 1.42 Å (a C-C bond) it is."""
    atoms, missing, others, sim, residuals = _missing_one(noise_std=20.0)
    target = atoms.positions[missing]
    near = np.vstack([others.positions, target + [0.6, 0.0, 0.0]])
    sites, _ = unexplained_sites(residuals, sim.angles_deg, sim.pixel_size_A, near, sigma_A=0.6)
    assert len(sites) == 0 or cKDTree(near).query(sites)[0].min() > 1.0
    bond = np.vstack([others.positions, target + [1.42, 0.0, 0.0]])
    sites, _ = unexplained_sites(residuals, sim.angles_deg, sim.pixel_size_A, bond, sigma_A=0.6)
    assert len(sites) == 1 and np.linalg.norm(sites[0] - target) < 0.5


def test_a_faint_atom_where_an_atom_could_be_is_found_only_given_the_hard_core():
    """0.15 of the buried atom's mass left in the residual, under ten times the noise: its
    back-projection peaks at 3.7 noise standard deviations, under the 4.9 no noise peak reaches in
    the whole volume, over the 2.8 of the one place the fit leaves (297 voxels at least the Au
    hard core, 2.0 Å, from every Gaussian: atoms/holes.py).  Without the hard core no site; with
    it one, on the atom (within 0.75 Å: a voxel maximum of a ridge along the missing wedge)."""
    atoms, missing, others, sim, _ = _missing_one(noise_std=20.0)
    clean = simulate_gaussian_tilt_series(atoms, sim.angles_deg, noise_std=0.0).projections
    fitted = simulate_gaussian_tilt_series(others, sim.angles_deg, noise_std=0.0).projections
    residuals = 10 * (sim.projections - clean) + 0.15 * (clean - fitted)
    args = (residuals, sim.angles_deg, sim.pixel_size_A, others.positions)
    assert len(unexplained_sites(*args, sigma_A=0.6)[0]) == 0
    sites, _ = unexplained_sites(*args, sigma_A=0.6, hard_core_A=2.0)
    assert len(sites) == 1 and np.linalg.norm(sites[0] - atoms.positions[missing]) < 0.75


def test_a_vacancy_in_a_complete_fit_gives_no_site_given_the_hard_core():
    """The same sphere with its middle atom absent from the particle and the fit alike: the
    residual is noise (ten times the last test's), and the place an atom could be is searched at
    its lower level without a site, for three noise seeds (the level's 5% false-alarm rate)."""
    atoms = spherical_particle("Au", radius_A=6.0)
    middle = int(np.argmin(np.linalg.norm(atoms.positions - atoms.positions.mean(0), axis=1)))
    vacancy = AtomSet(np.delete(atoms.positions, middle, axis=0), species=np.delete(np.asarray(atoms.species), middle))
    angles = parse_tilts("limited")
    clean = simulate_gaussian_tilt_series(vacancy, angles, noise_std=0.0)
    for seed in (1, 2, 3):
        noisy = simulate_gaussian_tilt_series(vacancy, angles, noise_std=200.0, seed=seed)
        sites, _ = unexplained_sites(
            noisy.projections - clean.projections,
            noisy.angles_deg,
            noisy.pixel_size_A,
            vacancy.positions,
            sigma_A=0.6,
            hard_core_A=2.0,
        )
        assert len(sites) == 0


def test_the_random_field_level_of_a_tensor_is_that_of_its_array():
    """The residual search reads the level on the run's device: the same three gradient
    variances in float64, so the same level to float64 rounding."""
    from gaussian_atoms_method.atoms.peaks import random_field_threshold
    from gaussian_atoms_method.atoms.volume_filters import gaussian_filter

    field = gaussian_filter(
        torch.randn(40, 48, 36, generator=torch.Generator().manual_seed(4), dtype=torch.float64), 1.5
    ).numpy()
    assert abs(random_field_threshold(torch.from_numpy(field), 0.05) - random_field_threshold(field, 0.05)) < 1e-9


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_the_search_on_cuda_finds_the_cpu_sites():
    """On a GPU the filter, the noise reading (numpy's median, by two order statistics) and the
    maxima run on the device: the same site to a voxel, the same mass to float32's back-projection
    rounding (1e-4)."""
    atoms, missing, others, sim, residuals = _missing_one(noise_std=20.0)
    found = [
        unexplained_sites(
            residuals, sim.angles_deg, sim.pixel_size_A, others.positions, float(sim.truth.sigmas[0]), device=d
        )
        for d in ("cpu", "cuda")
    ]
    (cpu_sites, cpu_masses), (gpu_sites, gpu_masses) = found
    assert cpu_sites.shape == gpu_sites.shape == (1, 3)
    assert np.abs(cpu_sites - gpu_sites).max() <= sim.pixel_size_A + 1e-9
    assert np.allclose(cpu_masses, gpu_masses, rtol=1e-4)


def _maxima_heights(field):
    from scipy.ndimage import maximum_filter

    peak = (field == maximum_filter(field, size=3, mode="wrap")) & (field > 0)
    return field[peak]


def test_the_discovery_level_holds_its_rate_and_stays_family_wise_on_noise():
    """Smoothed white noise (64^3 voxels, 2 voxels' blur, unit variance): with no peak of its
    own the discovery level is the family-wise one whenever no noise peak reaches that (three
    seeds); with 60 planted peaks of 8 standard deviations it falls below it, and the noise
    peaks above it (the planted ones' places excluded) are at most a few, as the rate (5% of the
    peaks above it: 3 expected at most) allows."""
    from scipy.ndimage import gaussian_filter

    from gaussian_atoms_method.atoms.peaks import discovery_level, level_for, resolution_elements

    for seed in (1, 2, 3):
        rng = np.random.default_rng(seed)
        noise = gaussian_filter(rng.standard_normal((64, 64, 64)), 2.0, mode="wrap")  # no edge: a stationary field
        noise /= noise.std()
        resels = resolution_elements(noise)
        family_wise = level_for(resels, 0.05)
        heights = _maxima_heights(noise)
        level = discovery_level(heights, resels, 0.05, family_wise)
        assert level == family_wise or heights.max() > family_wise
        planted = noise.copy()
        places = rng.integers(4, 60, size=(60, 3))
        planted[tuple(places.T)] += 8.0
        level = discovery_level(_maxima_heights(planted), resels, 0.05, family_wise)
        assert level < family_wise
        mask = np.ones(noise.shape, bool)
        for x, y, z in places:
            mask[max(x - 3, 0) : x + 4, max(y - 3, 0) : y + 4, max(z - 3, 0) : z + 4] = False
        assert int((_maxima_heights(np.where(mask, noise, 0.0)) > level).sum()) <= 6


def test_a_second_look_proposes_each_open_place_with_positive_residual_mass():
    """The faint buried atom of the test above (0.15 of its mass, under ten times the noise): the
    second look's places (every local maximum of positive mass in the residual's smoothed
    back-projection at least the hard core from every Gaussian) include one on the atom (within
    0.75 Å, a voxel maximum of a ridge along the missing wedge), every one of them at least the
    hard core from every Gaussian and from each other; with the residual's sign turned (a
    deficit there, no missing mass) none lies on it."""
    from gaussian_atoms_method.atoms.residual_sites import open_place_peaks

    atoms, missing, others, sim, _ = _missing_one(noise_std=20.0)
    clean = simulate_gaussian_tilt_series(atoms, sim.angles_deg, noise_std=0.0).projections
    fitted = simulate_gaussian_tilt_series(others, sim.angles_deg, noise_std=0.0).projections
    noise = 10 * (sim.projections - clean)
    for sign in (1.0, -1.0):
        residuals = noise + sign * 0.15 * (clean - fitted)
        places = open_place_peaks(residuals, sim.angles_deg, sim.pixel_size_A, others.positions, 2.0)
        assert len(places) == 0 or cKDTree(others.positions).query(places)[0].min() >= 2.0
        if len(places) > 1:
            assert cKDTree(places).query(places, k=2)[0][:, 1].min() >= 2.0
        on_atom = len(places) and np.linalg.norm(places - atoms.positions[missing], axis=1).min() < 0.75
        assert bool(on_atom) == (sign > 0)


def test_a_place_of_pure_noise_reads_a_standard_normal_significance():
    """``proposal_significance`` at 64 places beyond every atom's reach (its neighbours none) in a
    residual of white noise of a known level: the score of an atom's template over its noise's
    standard deviation is standard normal, so the 64 read a mean within 0.45 and a standard
    deviation within 0.7-1.35 (four standard errors of each for 64 independent draws; places 3 Å
    apart, an atom's template overlapping its neighbour's by exp(-9 / (4 x 0.6^2)) < 0.2%)."""
    from gaussian_atoms_method.atoms.proposal_test import proposal_significance
    from gaussian_atoms_method.physics.geometry import detector_axes_of

    atoms = spherical_particle("Au", radius_A=4.0)
    angles = parse_tilts("limited")
    clean = simulate_gaussian_tilt_series(atoms, angles, noise_std=0.0, margin_A=20.0)
    noisy = simulate_gaussian_tilt_series(atoms, angles, noise_std=20.0, seed=5, margin_A=20.0)
    grid = np.array(
        [
            [x, y, z]
            for x in (-13.5, -10.5, 10.5, 13.5)
            for y in (-10.5, -7.5, -4.5, -1.5, 1.5, 4.5, 7.5, 10.5)
            for z in (-1.5, 1.5)
        ]
    )
    axes = detector_axes_of(noisy.angles_deg, "y")
    n = len(atoms.positions)
    z, _ = proposal_significance(
        grid, atoms.positions, np.full(n, 0.6), np.ones(n), axes, noisy.projections - clean.projections,
        noisy.pixel_size_A, [(side - 1) / 2.0 for side in noisy.projections.shape[1:]], 20.0,
    )  # fmt: skip
    assert len(z) == 64, z
    assert abs(float(z.mean())) < 0.45
    assert 0.7 < float(z.std()) < 1.35


@pytest.mark.parametrize("shape", ["ball", "slab"])
def test_the_hull_test_through_its_inscribed_and_outer_balls_is_the_test_against_every_facet(shape):
    """Points nearer the centre than the nearest facet are inside and those beyond the farthest
    Gaussian outside; only the shell between is tested facet by facet (atoms/holes.py), with the
    same answer as testing every point so."""
    from gaussian_atoms_method.atoms.holes import OpenPlaces, _ball_of, _facets, _inside

    rng = np.random.default_rng(3)
    if shape == "ball":
        atoms = rng.normal(size=(6000, 3))
        atoms = 20.0 * atoms[np.linalg.norm(atoms, axis=1) < 1.0][:2000]
    else:
        atoms = rng.uniform(-1.0, 1.0, size=(500, 3)) * np.array([30.0, 30.0, 3.0])
    points = rng.uniform(atoms.min(axis=0) - 3.0, atoms.max(axis=0) + 3.0, size=(50_000, 3))
    facets = _facets(atoms)
    every_facet = _inside(points, facets)
    assert 0.05 < every_facet.mean() < 0.95
    assert np.array_equal(_inside(points, facets, *_ball_of(atoms)), every_facet)
    places = OpenPlaces(atoms, 2.0)
    clear = places.tree.query(points)[0] >= 2.0
    assert np.array_equal(places(points), clear & every_facet)
