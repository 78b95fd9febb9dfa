"""The convergence check and the result files, each on a constructed case (no training)."""

import time

import numpy as np
import pytest
import torch

from gaussian_atoms_method.atoms.atom_set import AtomSet, read_atoms
from gaussian_atoms_method.nerfstudio_layer.convergence import ConvergenceCheck
from gaussian_atoms_method.nerfstudio_layer.results import write_snapshot


def test_convergence_needs_two_settled_checks_in_a_row():
    """Precision 0.1 Å per axis (0.17 Å in 3D); a step of 0.01 Å is settled, 1 Å is not; a
    change of count starts again; the noise from the first check is passed back later."""
    seen = []

    def precision(noise):
        seen.append(noise)
        return np.full((4, 3), 0.1), 7.0

    check = ConvergenceCheck(warmup_length=100, refine_every=100)
    length_scale = 0.01  # normalised per Å: 1 Å = 0.01
    positions = torch.arange(4.0)[:, None] * torch.tensor([0.03, 0.0, 0.0])  # 3 Å apart
    assert not check.update(50, positions, length_scale, precision)  # not a check step
    assert not check.update(100, positions, length_scale, precision)  # nothing to compare with
    assert not check.update(200, positions + 0.0001, length_scale, precision)  # settled once
    assert check.update(300, positions + 0.0002, length_scale, precision)  # twice
    assert not check.update(400, positions + 0.0102, length_scale, precision)  # moved 1 Å
    assert not check.update(500, positions[:3] + 0.0102, length_scale, precision)  # one Gaussian fewer
    assert seen[0] is None and set(seen[1:]) == {7.0}


def test_convergence_matches_atoms_not_indices_and_tolerates_its_share_of_changes():
    """The same atoms in another order are the same atoms (a prune and a densify reorder the
    Gaussians); with changed_fraction 0.25, one Gaussian of four added or removed still counts
    as settled, two do not."""

    def precision(noise):
        return np.full((4, 3), 0.1), 7.0

    positions = torch.arange(4.0)[:, None] * torch.tensor([0.03, 0.0, 0.0])
    check = ConvergenceCheck(warmup_length=0, refine_every=1, changed_fraction=0.25, match_distance=0.007)
    assert not check.update(1, positions, 0.01, precision)
    assert not check.update(2, positions[[2, 0, 3, 1]], 0.01, precision)
    assert check.update(3, positions[[3, 1, 0]], 0.01, precision)  # one went: settled twice
    assert not check.update(4, positions[[3]], 0.01, precision)  # two went
    moved = ConvergenceCheck(warmup_length=0, refine_every=1, changed_fraction=0.25, match_distance=0.007)
    assert not moved.update(1, positions, 0.01, precision) and not moved.update(2, positions, 0.01, precision)
    assert not moved.update(3, positions + torch.tensor([0.008, 0.0, 0.0]), 0.01, precision)  # farther than the match distance: all new


def test_convergence_without_a_tilt_series_never_stops():
    check = ConvergenceCheck(warmup_length=0, refine_every=1)
    assert not any(check.update(s, torch.zeros(2, 3), 1.0, lambda noise: None) for s in range(5))


def test_snapshots_hold_the_atoms_and_a_time_line_per_step(tmp_path):
    atoms = AtomSet(np.array([[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]]), sigmas=[0.6, 0.7], amplitudes=[1.0, 2.0])
    write_snapshot(atoms, tmp_path / "snapshots", 100, 7, 0)
    write_snapshot(atoms, tmp_path / "snapshots", 200, 5, 123)
    back = read_atoms(tmp_path / "snapshots" / "step-000200.csv")
    np.testing.assert_allclose(back.positions, atoms.positions)
    lines = (tmp_path / "snapshots" / "times.csv").read_text().splitlines()
    assert [line.split(",")[0] for line in lines] == ["100", "200"] and lines[1].endswith(",5,123")
    assert float(lines[1].split(",")[1]) == pytest.approx(time.time(), abs=60)
