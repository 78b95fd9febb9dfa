"""Matching predicted to true atoms one-to-one within 0.75 Å."""

import numpy as np
import pytest

from gaussian_atoms_method.metrics import match_atoms, score_atoms


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
