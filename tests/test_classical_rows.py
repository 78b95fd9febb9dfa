"""SIRT on the FBP's sparse matrix, ASTRA's rows and the benchmark's classical rows."""

import sys

import numpy as np
import pytest

from gaussian_atoms_method.atoms.matching import score_atoms
from gaussian_atoms_method.harness import time_to_accuracy
from gaussian_atoms_method.harness.astra_rows import astra_unavailable
from gaussian_atoms_method.harness.simulate import parse_tilts, simulate_tilt_series, spherical_particle
from gaussian_atoms_method.physics.reconstruction import (
    backprojection_matrix,
    filtered_backprojection,
    sirt,
    slice_sinograms,
)


def _series():
    atoms = spherical_particle("Au", 6.0)
    return atoms, simulate_tilt_series(
        atoms, parse_tilts("-70:5:70"), potential="gaussian", detector_pixels=64, noise_std=2.0
    )


def test_sirt_reduces_the_residual_and_agrees_with_fbp():
    """Each SIRT iterate explains the sinograms better than the last (it minimises a weighted
    residual), and its slices have FBP's orientation (the same matrix, transposed)."""
    _, sim = _series()
    sino, length, _ = slice_sinograms(sim.projections)
    matrix = backprojection_matrix(sim.angles_deg, length, length).float().to_dense()
    measured = np.pad(sino.transpose(2, 1, 0), ((0, 0), (0, 1), (0, 0))).reshape(-1, sino.shape[0])
    misfits, last = [], None
    for _, slices in sirt(sino, sim.angles_deg, (2, 8, 32)):
        projected = matrix.T.numpy() @ slices.reshape(len(sino), -1).numpy().T
        misfits.append(np.linalg.norm(projected - measured))
        last = slices.numpy()
    assert misfits[0] > misfits[1] > misfits[2] and last.min() >= 0
    fbp = filtered_backprojection(sino, sim.angles_deg)
    assert np.corrcoef(last.ravel(), fbp.ravel())[0, 1] > 0.8


def test_classical_rows_trace_atoms_where_the_truth_is():
    """SIRT + tracing finds the cluster's atoms at every checkpoint, rows in iteration order."""
    atoms, sim = _series()

    class Series:
        projections, angles_deg, pixel_size_A, tilt_axis = sim.projections, sim.angles_deg, sim.pixel_size_A, "y"
        centre_px, tilt_axis_angle_deg, origin_A = None, 0.0, np.zeros(3)

    rows = list(time_to_accuracy.classical_rows(Series, "sirt", sirt_iterations=(20, 60)))
    assert [step for step, _, _ in rows] == [20, 60] and all(seconds > 0 for _, seconds, _ in rows)
    for _, _, positions in rows:
        s = score_atoms(positions, atoms.positions)
        assert s["tpr"] >= 0.9 and s["fp_per_true_atom"] <= 0.2, s
    with pytest.raises(ValueError, match="classical"):
        next(time_to_accuracy.classical_rows(Series, "art"))


def test_astra_rows_skipped_with_one_line(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "astra", None)  # an import of it fails
    reason = astra_unavailable(gpu=False)
    assert reason and "astra-toolbox" in reason and "\n" not in reason

    class Series:
        projections, angles_deg, pixel_size_A, tilt_axis = np.zeros((3, 9, 9)), np.array([-10.0, 0.0, 10.0]), 0.25, "y"
        centre_px, tilt_axis_angle_deg, origin_A = None, 0.0, np.zeros(3)

    assert list(time_to_accuracy.classical_rows(Series, "astra-sirt")) == []
    assert capsys.readouterr().out.strip() == reason


def test_astra_fbp_slice_has_our_orientation():
    """ASTRA's FBP of our sinograms, placed as ours, correlates with our FBP (same geometry)."""
    pytest.importorskip("astra")
    from gaussian_atoms_method.harness.astra_rows import astra_slices

    _, sim = _series()
    sino, _, _ = slice_sinograms(sim.projections)
    ((_, slices),) = astra_slices(sino, sim.angles_deg, "fbp")
    ours = filtered_backprojection(sino, sim.angles_deg)
    assert np.corrcoef(slices.ravel(), ours.ravel())[0, 1] > 0.95


def test_benchmark_refuses_sirt_iterations_out_of_order_in_one_line(tmp_path, capsys):
    from gaussian_atoms_method.cli import entrypoint

    with pytest.raises(SystemExit) as info:
        entrypoint(
            [
                "benchmark",
                "--data",
                str(tmp_path / "series"),
                "--output",
                str(tmp_path / "out"),
                "--sirt-iterations",
                "25",
                "10",
            ]
        )
    err = capsys.readouterr().err
    assert info.value.code == 2 and err.count("\n") == 1 and "--sirt-iterations" in err
    assert not (tmp_path / "out").exists()
