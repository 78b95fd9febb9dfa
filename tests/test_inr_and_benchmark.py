"""The INR baseline's geometry, and the accuracy benchmark end to end on a tiny particle."""

import csv

import numpy as np
import pytest
import torch

from gaussian_atoms_method.atoms.atom_set import AtomSet
from gaussian_atoms_method.harness.inr import fit_inr
from gaussian_atoms_method.harness.simulate import parse_tilts, simulate_tilt_series
from gaussian_atoms_method.harness.tracing import trace_atoms


def test_inr_puts_atoms_where_our_convention_says():
    """Two atoms, clean data: after a short fit the traced peaks sit within 0.25 Å of the truth
    (a sign or axis error would put them Å away); the caller's torch generator is left as it was
    (the layers' initial weights come from the fit's own seed)."""
    atoms = AtomSet(np.array([[1.5, -1.0, 0.8], [-1.2, 0.9, -1.1]]), species=["Au", "Au"])
    torch.manual_seed(123)
    callers = torch.random.get_rng_state()
    sim = simulate_tilt_series(atoms, parse_tilts("-90:5:85"), potential="gaussian", detector_pixels=32, noise_std=0.0)
    vol = fit_inr(
        sim.projections,
        sim.angles_deg,
        0.25,
        steps=400,
        rays_per_step=512,
        samples_per_ray=32,
        frequency_std_per_A=0.625,
        hidden=64,
        density_scale=1.0,
        learning_rate=5e-3,
    )
    assert torch.equal(torch.random.get_rng_state(), callers)
    idx, _ = trace_atoms(vol.data, vol.spacing_A)
    found = vol.index_to_A(idx)
    assert len(found) == 2
    d = np.linalg.norm(found[:, None] - atoms.positions[None], axis=-1).min(axis=1)
    assert d.max() < 0.25


def test_benchmark_accuracy_tiny(tmp_path):
    """Simulate (Lobato), reconstruct, trace, evaluate and tabulate; a rerun resumes."""
    pytest.importorskip("abtem")
    from gaussian_atoms_method.harness.benchmark import AccuracyBenchmark

    bench = AccuracyBenchmark(
        output=tmp_path, particles=("au",), tilts=("-70:10:70",), noise=(20.0,), methods=("fbp", "sart"), scale=0.2
    )
    rows = bench.run()
    assert [r["method"] for r in rows] == ["fbp", "sart"]
    with open(tmp_path / "results.csv") as f:
        table = list(csv.DictReader(f))
    assert len(table) == 2 and (tmp_path / "results.md").is_file() and (tmp_path / "accuracy_vs_noise.png").is_file()
    for r in rows:
        # A ~60-atom cluster with 15 tilts at high signal: the baselines find (nearly) every atom.
        assert r["tpr"] >= 0.9 and 0 < r["ssim"] <= 1
    evaluation = tmp_path / "runs" / "au--70:10:70-noise20" / "fbp" / "evaluation.json"
    evaluation.write_text(evaluation.read_text().replace('"tpr"', '"tpr_marker": 1, "tpr"'))
    again = bench.run()  # finished runs are read back, not recomputed
    assert again[0]["tpr"] == rows[0]["tpr"] and "tpr_marker" in evaluation.read_text()


def test_train_ours_removes_the_previous_run_of_its_fixed_name(tmp_path, monkeypatch):
    """The harness's runs have a fixed name (``ours/gaussian-atoms/run``): a rerun into the same
    directory starts from an empty one, so a previous run's snapshots (whose times
    ``benchmark`` reads) are not mixed with its own."""
    import subprocess

    from gaussian_atoms_method.atoms.atom_set import write_atoms
    from gaussian_atoms_method.harness import benchmark

    run = tmp_path / "ours" / "gaussian-atoms" / "run"
    (run / "snapshots").mkdir(parents=True)
    (run / "snapshots" / "times.csv").write_text("50,1.0,10,0\n")

    def fake_run(cmd, **kwargs):  # the training subprocess: writes only its atoms
        assert not (run / "snapshots").exists()
        run.mkdir(parents=True)
        write_atoms(AtomSet(positions=np.zeros((1, 3)), sigmas=np.ones(1), amplitudes=np.ones(1)), run / "atoms.xyz")
        return subprocess.CompletedProcess(cmd, 0, "", "")

    monkeypatch.setattr(benchmark.subprocess, "run", fake_run)
    atoms, _ = benchmark.train_ours(tmp_path / "data", tmp_path)
    assert len(atoms) == 1 and not (run / "snapshots").exists()
