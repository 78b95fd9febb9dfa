"""Species from masses, and the export verb's formats read back by ASE."""

import json
import subprocess
import sys
from pathlib import Path

import ase.io
import numpy as np
import pytest

from gaussian_atoms_method.atoms.atom_set import AtomSet, write_atoms
from gaussian_atoms_method.atoms.species import classify_species, kmeans_1d


def test_classify_two_species_by_mass():
    """Fe and Pt masses a factor 3 apart with 15% log-normal scatter: the two means are 7.3
    standard deviations apart, so only atoms beyond 3.7 sigma (about 0.02%, here 2 of 500 with
    this seed) fall on the wrong side; heavier mass -> Pt whatever order the elements are given
    in; separation d' above 5."""
    rng = np.random.default_rng(0)
    truth = np.array(["Fe"] * 300 + ["Pt"] * 200)
    masses = np.where(truth == "Pt", 3.0, 1.0) * np.exp(rng.normal(scale=0.15, size=len(truth)))
    for elements in (["Fe", "Pt"], ["Pt", "Fe"]):
        species, report = classify_species(masses, elements)
        assert np.mean(species == truth) >= 0.995
        assert abs(report["counts"]["Pt"] - 200) <= 3
        assert report["separation"]["Fe/Pt"] > 5
    with pytest.raises(ValueError, match="unknown element 'Xx'"):
        classify_species(masses, ["Fe", "Xx"])


def test_one_population_gets_one_element_whatever_the_elements_named():
    """A pure particle's masses (one log-normal population, 10% scatter) exported as Fe,Pt: the
    mixture picks one component, so no atom is called Fe; a real Fe/Pt mixture at the same
    scatter is split (Ashman's D far above 2)."""
    rng = np.random.default_rng(3)
    pure = 2.0 * np.exp(rng.normal(scale=0.10, size=600))
    species, report = classify_species(pure, ["Fe", "Pt"])
    assert set(species) == {"Pt"} and report["separated"] is False and report["populations"] == 1
    mixed = np.where(rng.uniform(size=600) < 0.5, 1.0, 3.0) * np.exp(rng.normal(scale=0.10, size=600))
    species, report = classify_species(mixed, ["Fe", "Pt"])
    assert report["separated"] is True and set(species) == {"Fe", "Pt"}


def test_a_run_names_its_atoms_by_the_series_species(capsys):
    """The run's report (``engine.results.name_species``): one element names every atom; two
    elements a factor 3 apart in mass (15% scatter) name each atom by its mass, the heavier
    population Pt, and the counts are printed; fewer atoms than elements take the heaviest."""
    from gaussian_atoms_method.engine.results import name_species

    rng = np.random.default_rng(1)
    truth = np.array(["Fe"] * 150 + ["Pt"] * 100)
    masses = np.where(truth == "Pt", 3.0, 1.0) * np.exp(rng.normal(scale=0.15, size=len(truth)))
    species, confidence = name_species(masses, ("Ta",))
    assert set(species) == {"Ta"} and np.all(confidence == 1.0)
    assert np.mean(name_species(masses, ("Pt", "Fe"))[0] == truth) >= 0.99
    assert "Pt" in capsys.readouterr().out
    species, confidence = name_species(masses[:1], ("Fe", "Pt"))
    assert list(species) == ["Pt"] and np.isnan(confidence).all()


def test_each_atoms_element_confidence_is_how_often_such_an_element_is_right():
    """Two elements only 1.6 times apart in mass with 15% scatter (populations 3.1 standard
    deviations apart: about one atom in twenty misnamed): each atom's element confidence is
    calibrated. Over 2,000 atoms the mean confidence is the share named right (to 0.02: the
    mixture's own estimate against 2,000 draws), the atoms named wrong doubt it (mean confidence
    under 0.8), and those with confidence above 0.95 are right 0.97 of the time or more."""
    from gaussian_atoms_method.atoms.species import classify_species

    rng = np.random.default_rng(4)
    truth = np.array(["Co"] * 1200 + ["Pt"] * 800)
    masses = np.where(truth == "Pt", 1.6, 1.0) * np.exp(rng.normal(scale=0.15, size=len(truth)))
    species, report = classify_species(masses, ["Pt", "Co"])
    right, confidence = species == truth, report["confidence"]
    assert 0.90 < right.mean() < 0.99
    assert abs(confidence.mean() - right.mean()) < 0.02
    assert confidence[~right].mean() < 0.8
    assert right[confidence > 0.95].mean() >= 0.97


def test_each_atom_is_named_by_the_element_bayes_rule_makes_most_probable():
    """A light element's masses scattered twice as widely as a heavier one's (16% against 8% in
    log mass, means 0.75 apart: a light atom among heavier neighbours lends and borrows more of
    its mass): k-means's nearest centre puts the boundary halfway and names 6-19 of 2,000 atoms
    wrong over five draws; Bayes' rule, which each atom's confidence already states, moves it
    towards the narrow population and names 1-3 wrong, and the confidence stays calibrated (its
    mean the share named right to 0.002)."""
    from gaussian_atoms_method.atoms.species import classify_species, kmeans_1d

    for seed in range(5):
        rng = np.random.default_rng(seed)
        truth = np.array(["Ni"] * 1000 + ["Pd"] * 1000)
        heavy = truth == "Pd"
        log_mass = np.where(heavy, 0.75, 0.0) + rng.normal(size=len(truth)) * np.where(heavy, 0.08, 0.16)
        species, report = classify_species(np.exp(log_mass), ["Pd", "Ni"])
        nearest = np.array(["Ni", "Pd"])[kmeans_1d(log_mass, 2)]
        assert np.sum(species != truth) <= 3 < np.sum(nearest != truth)
        assert abs(report["confidence"].mean() - np.mean(species == truth)) < 0.002


def test_kmeans_orders_clusters_by_mean():
    labels = kmeans_1d(np.array([5.0, 5.1, 0.0, 0.1, 9.9, 10.0]), 3)
    np.testing.assert_array_equal(labels, [1, 1, 0, 0, 2, 2])


def test_export_round_trips_through_ase(tmp_path):
    run = tmp_path / "run"
    # 40 atoms on a 2.5 Å grid: 20 light (amplitude 10) and 20 three times heavier, 2% scatter
    grid = np.stack(np.meshgrid(np.arange(4), np.arange(5), np.arange(2), indexing="ij"), -1).reshape(-1, 3) * 2.5
    heavy = np.arange(40) % 2 == 1
    amplitudes = np.where(heavy, 30.0, 10.0) * np.exp(np.random.default_rng(0).normal(scale=0.02, size=40))
    atoms = AtomSet(grid.astype(float), sigmas=np.full(40, 0.6), amplitudes=amplitudes)
    write_atoms(atoms, run / "atoms.xyz")
    (run / "config.yml").write_text("method_name: gaussian-atoms\n")
    exe = Path(sys.executable).parent / "gaussian-atoms"
    for suffix in (".extxyz", ".csv", ".cif"):
        out = tmp_path / f"out{suffix}"
        proc = subprocess.run(
            [exe, "export", "--load-config", run / "config.yml", "--output", out, "--species", "Fe,Pt"],
            capture_output=True,
            text=True,
        )
        assert proc.returncode == 0, proc.stderr
        if suffix != ".csv":
            back = ase.io.read(out)
            # A CIF cell cannot hold negative coordinates: shifted by half the cell, as documented.
            shift = back.cell.lengths() / 2 if suffix == ".cif" else 0.0
            np.testing.assert_allclose(back.get_positions() - shift, atoms.positions, atol=1e-4)
            assert back.get_chemical_symbols() == np.where(heavy, "Pt", "Fe").tolist()
        if suffix == ".extxyz":
            np.testing.assert_allclose(back.arrays["sigma_A"], atoms.sigmas)
            np.testing.assert_allclose(back.arrays["amplitude"], atoms.amplitudes)
    assert json.loads(proc.stdout.splitlines()[0])["species"]["counts"] == {"Fe": 20, "Pt": 20}
    missing = subprocess.run(
        [exe, "export", "--load-config", tmp_path / "none" / "config.yml", "--output", tmp_path / "x.xyz"],
        capture_output=True,
        text=True,
    )
    assert missing.returncode == 2 and "config.yml: run config not found" in missing.stderr
