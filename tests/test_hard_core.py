"""The material's hard core: from its species, from the atoms found, kept while training, and the
report that obeys it (no pair inside it, non-atom populations set apart)."""

import math

import numpy as np
import pytest
import torch

from gaussian_atoms_method.atoms.hard_core import (
    COVALENT_FRACTION,
    SpeciesError,
    close_pairs,
    hard_core_from_positions,
    hard_core_from_species,
    most_apart,
    parse_species,
)
from gaussian_atoms_method.harness.particles import make_particle


def test_the_hard_core_from_species_lies_below_every_bond_of_the_material_and_above_a_split_atom():
    """Cordero's radii (Ta 1.70, Fe 1.32, Pt 1.36, C 0.76 Å) times the fraction: Ta 1.87 Å, below
    its 2.5-3.0 Å bonds and above the 1.65 Å pairs a misfit makes; Fe,Pt takes its smaller pair
    (Fe-Fe); carbon's 0.84 Å is below its triple bond (1.20 Å)."""
    assert hard_core_from_species("Ta") == pytest.approx(COVALENT_FRACTION * 3.40, abs=1e-9)
    assert 1.65 < hard_core_from_species("Ta") < 2.5
    assert hard_core_from_species("Fe,Pt") == pytest.approx(COVALENT_FRACTION * 2 * 1.32, abs=1e-9)
    assert hard_core_from_species(["Pt", "Fe"]) == hard_core_from_species("fe pt")
    assert hard_core_from_species("C") < 1.20
    for name, bond_A in [("Au", 2.88), ("Si", 2.35), ("Pd", 2.75), ("Ni", 2.49)]:
        assert 0.5 * bond_A < hard_core_from_species(name) < 0.7 * bond_A


def test_the_shortest_bond_lies_above_the_hard_core_by_the_position_allowance_and_below_real_bonds():
    """A specimen's true atoms come no closer than the shortest bond chemistry knows, 0.62 of the
    covalent radii (the Cr-Cr quintuple bond); the hard core sits below it by the room a measured
    pair needs.  Ta: 2.11 Å, under its 2.5-3.0 Å bonds; carbon's 0.94 Å under its triple bond."""
    from gaussian_atoms_method.atoms.hard_core import POSITION_ALLOWANCE, shortest_bond_from_species

    for name, bond_A in [("Ta", 2.5), ("Au", 2.88), ("Si", 2.35), ("C", 1.20), ("Fe,Pt", 2.48)]:
        shortest = shortest_bond_from_species(name)
        assert hard_core_from_species(name) < shortest < bond_A
        assert shortest - hard_core_from_species(name) == pytest.approx(POSITION_ALLOWANCE / 0.62 * shortest)
    assert shortest_bond_from_species("Ta") == pytest.approx(0.62 * 3.40, abs=1e-9)
    with pytest.raises(SpeciesError):
        shortest_bond_from_species("")


def test_species_are_parsed_and_unknown_ones_named():
    assert parse_species("Fe,Pt") == ("Fe", "Pt")
    assert parse_species(" ta ") == ("Ta",)
    assert parse_species(None) == ()
    with pytest.raises(SpeciesError, match="'Xx'"):
        parse_species("Fe,Xx")
    with pytest.raises(SpeciesError, match="at least one"):
        hard_core_from_species("")


def dart_thrown(n: int, box_A: float, closest_A: float, seed: int) -> np.ndarray:
    """An amorphous arrangement: ``n`` points in a cube, none closer than ``closest_A``."""
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < n:
        p = rng.uniform(0, box_A, 3)
        if not out or np.min(np.linalg.norm(np.asarray(out) - p, axis=1)) >= closest_A:
            out.append(p)
    return np.asarray(out)


def test_the_hard_core_read_from_data_ignores_a_made_up_pair_peak_below_the_first_shell():
    """Atoms of a dense random packing (none closer than 2.5 Å) and, beside 40% of them, a
    lighter partner 1.65 Å away (a misfit's pair: together they hold the atom's mass): the
    reading uses the heavy atoms alone, so the hard core lies above the pairs and below the
    material's shortest distance."""
    atoms = dart_thrown(300, 20.0, 2.5, seed=0)
    rng = np.random.default_rng(1)
    pick = rng.choice(len(atoms), 120, replace=False)
    direction = rng.normal(size=(len(pick), 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    positions = np.concatenate([atoms, atoms[pick] + 1.65 * direction])
    masses = np.concatenate([np.ones(len(atoms)), np.full(len(pick), 0.4)])
    masses[pick] = 0.6
    core, bond = hard_core_from_positions(positions, masses, typical_mass=1.0)
    assert 2.5 <= bond <= 3.2  # the first shell of the packing
    assert 1.65 < core < 2.5
    assert hard_core_from_positions(positions[:5], masses[:5], 1.0) == (math.inf, math.inf)


def test_the_heaviest_apart_keep_the_most_mass_the_hard_core_allows():
    """Given masses, ``most_apart`` keeps the set apart of the greatest mass.  A chain of three
    1.0 Å apart: the heaviest keeps its place, its neighbour goes, the third (2.0 Å from it) stays.
    A wide Gaussian of one atom's mass between two lighter atoms 2.8 Å apart: the two (1.7 atoms'
    mass); between two fragments of 0.3: the one atom."""
    positions = np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0], [10.0, 0, 0]])
    masses = np.array([5.0, 1.0, 2.0, 1.0])
    assert most_apart(positions, 1.5, masses).tolist() == [True, False, True, True]
    assert close_pairs(positions, 1.5).tolist() == [[0, 1], [1, 2]]
    assert close_pairs(positions, math.inf).shape == (0, 2)
    between = np.array([[0.0, 0, 0], [1.4, 0, 0], [-1.4, 0, 0]])
    assert most_apart(between, 1.87, np.array([1.0, 0.8, 0.9])).tolist() == [False, True, True]
    assert most_apart(between, 1.87, np.array([1.0, 0.3, 0.3])).tolist() == [True, False, False]
    assert most_apart(between[:2], 1.87, np.array([0.4, 0.6])).tolist() == [False, True]  # of a pair, the heavier
    cluster = np.random.default_rng(3).uniform(0, 5, (40, 3))  # one group: the greedy branch, heaviest first
    weights = np.random.default_rng(4).uniform(0.5, 1.5, 40)
    keep = most_apart(cluster, 1.87, weights)
    assert len(close_pairs(cluster[keep], 1.87)) == 0 and keep[np.argmax(weights)]


def test_the_most_atoms_apart_keep_no_pair_within_the_core_and_drop_none_they_could_keep():
    """``most_apart``: no kept pair closer than the distance, and every point set aside lies
    within it of a kept one (none could be added back). Small groups are solved exactly (a pair
    keeps one, a chain of three its ends, a triangle one, a square two); a cluster of 40 points
    in one group (the greedy branch) too."""
    d = 1.87
    pair, chain = np.array([[0.0, 0, 0], [1.5, 0, 0]]), np.array([[0.0, 0, 0], [1.5, 0, 0], [3.0, 0, 0]])
    triangle = np.array([[0.0, 0, 0], [1.5, 0, 0], [0.75, 1.3, 0]])
    square = np.array([[0.0, 0, 0], [1.5, 0, 0], [1.5, 1.5, 0], [0.0, 1.5, 0]])
    for points, kept in ((pair, 1), (chain, 2), (triangle, 1), (square, 2)):
        assert most_apart(points + 10.0, d).sum() == kept
    np.testing.assert_array_equal(most_apart(chain, d), [True, False, True])
    cluster = np.random.default_rng(3).uniform(0, 5, (40, 3))
    keep = most_apart(cluster, d)
    assert len(close_pairs(cluster[keep], d)) == 0 and keep.sum() < 40
    gaps = np.linalg.norm(cluster[~keep][:, None] - cluster[keep][None], axis=-1).min(axis=1)
    assert np.all(gaps < d)


def test_a_vacuum_population_is_labelled_non_atoms():
    """A carbon-like particle (atoms 1.42 Å apart) and around it a population of wider, lighter
    Gaussians more than 2 Å from any atom but close to each other (a probe's leftovers in the
    vacuum): the mixture gives them a class of their own, and the class lies outside the atoms'
    support, so every one of them is a non-atom while every atom stays."""
    from gaussian_atoms_method.atoms.classification import classify_gaussians

    atoms = make_particle("carbon", scale=0.35).positions
    rng = np.random.default_rng(2)
    shell = rng.normal(size=(4 * len(atoms), 3))
    shell /= np.linalg.norm(shell, axis=1, keepdims=True)
    radius = np.max(np.linalg.norm(atoms, axis=1))
    fog = shell * rng.uniform(radius + 2.5, radius + 6.0, size=(len(shell), 1))
    fog = fog[np.min(np.linalg.norm(fog[:, None] - atoms[None], axis=2), axis=1) > 2.0][: len(atoms) // 2]
    positions = np.concatenate([atoms, fog])
    masses = np.concatenate([rng.normal(0.0087, 0.0008, len(atoms)), rng.normal(0.0054, 0.0008, len(fog))])
    sigmas = np.concatenate([rng.normal(0.50, 0.03, len(atoms)), rng.normal(0.83, 0.05, len(fog))])
    result = classify_gaussians(np.abs(masses), np.abs(sigmas), positions)
    assert result.atoms[: len(atoms)].mean() >= 0.99
    assert not result.atoms[len(atoms) :].any()


def density_control(hard_core_A: float = 1.87):
    """A density control in Å (length scale 1) with the hard core of the species given."""
    from gaussian_atoms_method.density.strategy import DensityControl

    return DensityControl(
        length_scale=1.0,
        max_log_amplitude=50.0,
        generator=torch.Generator().manual_seed(0),
        half_extent=(20.0, 20.0, 20.0),
        hard_core_A=hard_core_A,
    )


def params_at(positions: np.ndarray, masses: np.ndarray, sigma: float = 0.5) -> dict:
    amp = np.asarray(masses) / (2 * math.pi * sigma**2) ** 1.5
    return {
        "means": torch.nn.Parameter(torch.as_tensor(positions, dtype=torch.float32)),
        "log_sigmas": torch.nn.Parameter(torch.full((len(positions), 1), math.log(sigma))),
        "log_amplitudes": torch.nn.Parameter(torch.log(torch.as_tensor(amp, dtype=torch.float32))[:, None]),
    }


def test_training_joins_a_split_atom_and_pushes_two_atoms_apart_to_the_hard_core():
    """Species set (hard core 1.87 Å): a pair 1.2 Å apart sharing one atom's mass becomes one
    Gaussian at its centre of mass; a pair 1.5 Å apart holding two atoms' mass stays two, moved
    apart to the hard core about its centre; atoms 2.5 Å apart are left alone."""
    lattice = np.stack(np.meshgrid(*[np.arange(4)] * 3, indexing="ij"), -1).reshape(-1, 3) * 2.5 - 10.0
    split = np.array([[5.0, 5.0, 5.0], [5.0, 5.0, 6.2]])
    two = np.array([[-15.0, 5.0, 5.0], [-15.0, 5.0, 6.5]])
    positions = np.concatenate([lattice, split, two])
    masses = np.concatenate([np.ones(len(lattice)), [0.6, 0.4], [1.0, 1.0]])
    params = params_at(positions, masses)
    dc = density_control()
    dc.reset(len(positions))
    optimizers = {k: torch.optim.Adam([p], lr=1e-3) for k, p in params.items()}
    removed = dc.join_close_pairs(params, optimizers)
    assert removed == 1 and dc.state.joined_close == 1
    means = params["means"].detach().double().numpy()
    assert len(means) == len(positions) - 1
    np.testing.assert_allclose(means[: len(lattice)], lattice, atol=1e-6)
    # the split atom: one Gaussian at the pair's centre of mass
    centre = 0.6 * split[0] + 0.4 * split[1]
    assert np.min(np.linalg.norm(means - centre, axis=1)) < 1e-5
    # the two atoms: 1.87 Å apart about their midpoint
    pushed = means[np.abs(means[:, 0] + 15.0) < 1e-6]
    assert len(pushed) == 2
    assert np.linalg.norm(pushed[0] - pushed[1]) == pytest.approx(1.87, abs=1e-5)
    np.testing.assert_allclose(pushed.mean(axis=0), two.mean(axis=0), atol=1e-5)


def test_a_new_gaussian_is_never_placed_within_the_hard_core():
    """Residual sites within the hard core of an atom are dropped; one beyond it is added."""
    positions = np.array([[0.0, 0, 0], [2.5, 0, 0]])
    params = params_at(positions, np.ones(2))
    dc = density_control()
    dc.reset(2)
    optimizers = {k: torch.optim.Adam([p], lr=1e-3) for k, p in params.items()}
    sites = torch.tensor([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [5.0, 0.0, 0.0]])
    added = dc.add(params, optimizers, sites, 0.5, torch.ones(3))
    assert added == 2
    np.testing.assert_allclose(params["means"].detach().numpy()[2:], sites[1:].numpy())


def test_an_atom_with_a_profile_the_model_lacks_is_fitted_without_a_reported_pair(tmp_path):
    """Every Au atom of a small fcc sphere is imaged with a satellite 1.2 Å beside it holding 28%
    of its mass (a profile no isotropic Gaussian has: a probe's tail on one side).  The fit,
    told the species (hard core 1.50 Å), reports every atom, no satellite as an atom, and no pair
    inside the hard core."""
    import subprocess
    import sys
    from pathlib import Path

    from dataparsers.tilt_series_format import write_tilt_series
    from gaussian_atoms_method.atoms.atom_set import AtomSet, read_atoms
    from gaussian_atoms_method.atoms.matching import score_atoms
    from gaussian_atoms_method.harness.simulate import parse_tilts, simulate_tilt_series, spherical_particle

    atoms = spherical_particle("Au", radius_A=6.0)
    direction = np.array([1.0, 0.5, 0.3]) / np.linalg.norm([1.0, 0.5, 0.3])
    satellites = AtomSet(atoms.positions + 1.2 * direction, species=["Ti"] * len(atoms))  # Z 22 of 79: 28% of the mass
    both = AtomSet(
        np.concatenate([atoms.positions, satellites.positions]), species=list(atoms.species) + list(satellites.species)
    )
    sim = simulate_tilt_series(both, parse_tilts("-70:5:70"), potential="gaussian", noise_std=20.0, seed=1)
    data = write_tilt_series(
        tmp_path / "series", sim.projections, sim.angles_deg, sim.pixel_size_A, truth=atoms, species="Au"
    )
    run = subprocess.run(
        [
            str(Path(sys.executable).parent / "gaussian-atoms"),
            "train",
            "--machine.device-type",
            "cpu",
            "--vis",
            "tensorboard",
            "--output-dir",
            str(tmp_path / "out"),
            "--experiment-name",
            "e",
            "--timestamp",
            "t",
            "tilt-series",
            "--data",
            str(data),
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
    reported = read_atoms(tmp_path / "out" / "e" / "gaussian-atoms" / "t" / "atoms.xyz")
    assert set(reported.species) == {"Au"}  # the series' one element names every reported atom
    found = reported.positions
    scores = score_atoms(found, atoms.positions)
    assert scores["tpr"] >= 0.95 and scores["fp_per_true_atom"] <= 0.05, scores
    assert len(close_pairs(found, hard_core_from_species("Au"))) == 0
