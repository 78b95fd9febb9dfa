"""Matching predicted to true atoms one-to-one within 0.75 Å."""

import numpy as np
import pytest

from gaussian_atoms_method.atoms.matching import match_atoms, score_atoms


def test_perfect_and_shifted():
    rng = np.random.default_rng(0)
    truth = rng.uniform(0, 30, size=(200, 3))
    s = score_atoms(truth, truth)
    assert s["tpr"] == 1.0 and s["fp_per_true_atom"] == 0.0 and s["rmsd_pm"] == 0.0
    shift = np.array([0.03, -0.04, 0.0])  # 5 pm
    s = score_atoms(truth + shift, truth)
    assert s["n_matched"] == 200
    assert s["rmsd_pm"] == pytest.approx(5.0, rel=1e-9)


def test_one_to_one():
    """Two predictions near one true atom: one match, one false positive."""
    truth = np.array([[0.0, 0.0, 0.0]])
    pred = np.array([[0.1, 0.0, 0.0], [-0.2, 0.0, 0.0]])
    s = score_atoms(pred, truth)
    assert s["n_matched"] == 1 and s["fp_per_true_atom"] == 1.0 and s["precision"] == 0.5
    assert s["rmsd_pm"] == pytest.approx(10.0)  # the closer one is kept


def test_maximum_matching_not_greedy():
    """Greedy nearest-first would match p0-t1 and leave t0 unmatched; the optimum matches both."""
    truth = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    pred = np.array([[0.6, 0.0, 0.0], [1.7, 0.0, 0.0]])
    pi, ti = match_atoms(pred, truth, 0.75)
    assert sorted(zip(pi.tolist(), ti.tolist())) == [(0, 0), (1, 1)]


def test_radius_edge_is_inclusive():
    truth = np.zeros((1, 3))
    assert score_atoms(np.array([[0.75, 0.0, 0.0]]), truth)["n_matched"] == 1
    assert score_atoms(np.array([[0.7501, 0.0, 0.0]]), truth)["n_matched"] == 0


def test_empty_sets():
    truth = np.zeros((3, 3))
    s = score_atoms(np.zeros((0, 3)), truth)
    assert s["tpr"] == 0.0 and np.isnan(s["rmsd_pm"]) and np.isnan(s["precision"])
    with pytest.raises(ValueError):
        match_atoms(truth, truth, radius_A=0.0)


def test_voxelise_gaussians_mass_and_position():
    from gaussian_atoms_method.harness.metrics import voxelise_gaussians

    pos = np.array([[0.3, -0.6, 1.1], [-1.5, 1.0, -0.4]])
    sig = np.array([0.5, 0.7])
    amp = np.array([2.0, 1.0])
    vol = voxelise_gaussians(pos, sig, amp, 0.1, (100, 100, 100), radius_sigmas=6.0)
    # Riemann sum of well-sampled Gaussians cut at 6 sigma: the integrated mass to 1e-6.
    mass = (amp * (2 * np.pi * sig**2) ** 1.5).sum()
    assert vol.sum() * 0.1**3 == pytest.approx(mass, rel=1e-6)
    # The value at a voxel equals the direct evaluation.
    i, j, k = 33, 24, 40
    r = (np.array([i, j, k]) - 49.5) * 0.1
    direct = (amp * np.exp(-((r - pos) ** 2).sum(1) / (2 * sig**2))).sum()
    assert vol[i, j, k] == pytest.approx(direct, rel=1e-9)


def test_volume_ssim_reports_its_reference():
    from gaussian_atoms_method.harness.metrics import volume_ssim, voxelise_gaussians

    pos = np.array([[0.0, 0.0, 0.0], [1.5, 0.0, 0.0]])
    ref = voxelise_gaussians(pos, np.array([0.5, 0.5]), np.ones(2), 0.25, (24, 24, 24))
    assert volume_ssim(ref, ref)["ssim"] == pytest.approx(1.0)
    moved = voxelise_gaussians(pos + 0.5, np.array([0.5, 0.5]), np.ones(2), 0.25, (24, 24, 24))
    out = volume_ssim(moved, ref)
    assert out["ssim"] < 0.9 and out["ssim_data_range"] == pytest.approx(ref.max() - ref.min())
    with pytest.raises(ValueError, match="shape"):
        volume_ssim(ref[:-1], ref)


def test_mean_shift_variant_removes_a_global_offset():
    rng = np.random.default_rng(2)
    truth = rng.uniform(0, 20, size=(100, 3))
    pred = truth + [0.3, -0.2, 0.1] + rng.normal(0, 0.02, (100, 3))
    plain = score_atoms(pred, truth)
    shifted = score_atoms(pred, truth, mean_shift=True)
    assert plain["rmsd_pm"] > 35 and shifted["rmsd_pm"] < 4.5  # 2 pm per axis -> ~3.5 pm
    np.testing.assert_allclose(shifted["shift_A"], [-0.3, 0.2, -0.1], atol=0.01)


def test_species_accuracy():
    truth = np.array([[0.0, 0, 0], [3.0, 0, 0], [6.0, 0, 0]])
    s = score_atoms(truth, truth, pred_species=["Fe", "Pt", "Pt"], true_species=["Fe", "Pt", "Fe"])
    assert s["species_accuracy"] == pytest.approx(2 / 3)


def test_voxelise_mixed_widths_bounded_memory():
    """One stray very wide Gaussian among narrow ones: every atom still lands, memory stays bounded."""
    from gaussian_atoms_method.harness.metrics import voxelise_gaussians

    rng = np.random.default_rng(0)
    pos = rng.uniform(-3, 3, size=(2000, 3))
    sig = np.full(2000, 0.3)
    sig[0] = 50.0  # wider than the box: its window is capped at the grid
    amp = np.ones(2000)
    vol = voxelise_gaussians(pos, sig, amp, 0.25, (32, 32, 32))
    i, j, k = np.round(pos[5] / 0.25 + 15.5).astype(int)
    assert vol[i, j, k] >= 1.0  # a narrow atom's own peak (plus the wide one's plateau) is there
    assert vol.min() > 0.9  # the wide Gaussian covers the whole box at nearly its peak


def test_interior_of_the_detector_footprint():
    """Positions at least the margin inside the zero-tilt footprint (rows along x, columns along
    y about centre_px, in the truth's frame): a 10 x 8 detector of 0.5 Å about its middle spans
    x in [-2.5, 2.5], y in [-2, 2] Å."""
    from dataparsers.tilt_series_format import TiltSeries
    from gaussian_atoms_method.harness.evaluation import inside_footprint

    views = np.random.default_rng(0).uniform(1, 2, (3, 10, 8))  # any views: the geometry is what counts
    series = TiltSeries(views, np.array([-30.0, 0.0, 30.0]), 0.5, origin_A=np.array([10.0, 0.0, 0.0]))
    positions = np.array([[10.0, 0.0, 5.0], [12.4, 0.0, 0.0], [12.6, 0.0, 0.0], [10.0, -1.4, 0.0], [10.0, -1.6, 0.0]])
    np.testing.assert_array_equal(inside_footprint(positions, series, 0.0), [True, True, False, True, True])
    np.testing.assert_array_equal(inside_footprint(positions, series, 0.5), [True, False, False, True, False])


def test_a_true_atom_beyond_the_field_is_neither_found_nor_missed_and_its_partner_is_not_false():
    """A truth wider than the field scored: the atom inside the field counts, the one outside
    does not, and a predicted atom on the outside one is neither found nor false."""
    truth = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0], [30.0, 0.0, 0.0]])
    pred = np.array([[0.1, 0.0, 0.0], [30.1, 0.0, 0.0], [10.0, 0.0, 0.0]])
    s = score_atoms(pred, truth, true_counted=np.array([True, True, False]))
    assert (s["n_true"], s["n_pred"], s["n_matched"], s["n_true_uncounted"]) == (2, 2, 1, 1)
    assert s["tpr"] == 0.5 and s["fp_per_true_atom"] == 0.5 and s["rmsd_pm"] == pytest.approx(10.0)


def test_evaluate_with_data_scores_the_truth_inside_the_footprint(tmp_path):
    """``evaluate --data`` on a series whose truth reaches past the detector (a film's whole
    model beside one sub-area) scores the true atoms inside the footprint, and says how many it
    left out."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    from dataparsers.tilt_series_format import write_tilt_series
    from gaussian_atoms_method.atoms.atom_set import AtomSet, write_atoms

    inside = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 1.0], [0.0, 3.0, -1.0]])
    truth = AtomSet(np.r_[inside, inside + [40.0, 0.0, 0.0]], species=np.full(6, "Au"))
    views = np.random.default_rng(0).random((3, 40, 40)).astype(np.float32)  # only their geometry is read
    data = write_tilt_series(tmp_path / "s", views, [-30.0, 0.0, 30.0], 0.25, truth=truth)
    write_atoms(AtomSet(inside + 0.05, species=np.full(3, "Au")), tmp_path / "pred.xyz")
    run = subprocess.run(
        [str(Path(sys.executable).parent / "gaussian-atoms"), "evaluate", "--pred", str(tmp_path / "pred.xyz")]
        + ["--data", str(data)],
        capture_output=True,
        text=True,
    )
    assert run.returncode == 0, run.stderr
    scores = json.loads(run.stdout)
    assert scores["tpr"] == 1.0 and scores["n_true"] == 3 and scores["n_true_uncounted"] == 3
    assert "(3 beyond the field not scored)" in run.stderr
