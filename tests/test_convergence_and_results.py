"""The convergence check and the result files, each on a constructed case (no training)."""

import time

import numpy as np
import pytest
import torch

from gaussian_atoms_method.atoms.atom_set import AtomSet, read_atoms
from gaussian_atoms_method.engine.convergence import ConvergenceCheck, mutual_nearest, places_changed
from gaussian_atoms_method.engine.results import read_snapshot_times, write_snapshot


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
    # farther than the match distance: all new
    assert not moved.update(3, positions + torch.tensor([0.008, 0.0, 0.0]), 0.01, precision)


def test_a_merge_or_split_within_the_hard_core_keeps_its_place_and_a_birth_counts_whole():
    """Ta's hard core (1.87 Å): two Gaussians of 0.75 and 0.7 atoms 2.0 Å apart merged into one
    of 1.45 at their mass-weighted mean lose no atom's worth (each parent lies within the hard
    core of the product); the split back does the same; a Gaussian pruned or born elsewhere
    counts whole, and a place whose mass changed counts the change."""
    core = 1.87
    atoms = np.array([[0.0, 0, 0], [2.6, 0, 0], [5.2, 0, 0]])
    worth = np.array([1.0, 0.75, 0.7])
    pair = np.array([[0.0, 0, 0], [2.6, 0, 0], [2.6, 0, 2.0]])  # the second along the beam
    merged = np.array([[0.0, 0, 0], [2.6, 0, 2.0 * 0.7 / 1.45]])
    m = mutual_nearest(pair, merged, 0.7)
    assert places_changed(pair, worth, merged, np.array([1.0, 1.45]), m, core) == pytest.approx(0.0)
    back = mutual_nearest(merged, pair, 0.7)
    assert places_changed(merged, np.array([1.0, 1.45]), pair, worth, back, core) == pytest.approx(0.0)
    # nothing links them within a match distance of 0.7 Å: counted by Gaussian, 2.9 atoms
    assert places_changed(pair, worth, merged, np.array([1.0, 1.45]), m, 0.7) == pytest.approx(2.9)
    gone = mutual_nearest(atoms, atoms[:2], 0.7)  # the third pruned
    assert places_changed(atoms, worth, atoms[:2], worth[:2], gone, core) == pytest.approx(0.7)
    born = np.vstack([atoms, [[9.0, 0, 0]]])
    assert places_changed(atoms, worth, born, np.append(worth, 1.2), mutual_nearest(atoms, born, 0.7), core) == (
        pytest.approx(1.2)
    )
    same = mutual_nearest(atoms, atoms, 0.7)  # every Gaussian matched: nothing changed
    assert places_changed(atoms, worth, atoms, worth * 1.1, same, core) == 0.0


def test_convergence_without_a_tilt_series_never_stops():
    check = ConvergenceCheck(warmup_length=0, refine_every=1)
    assert not any(check.update(s, torch.zeros(2, 3), 1.0, lambda noise: None) for s in range(5))


def test_snapshots_hold_the_atoms_and_a_time_line_per_step(tmp_path):
    atoms = AtomSet(np.array([[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]]), sigmas=[0.6, 0.7], amplitudes=[1.0, 2.0])
    first = write_snapshot(atoms, tmp_path / "snapshots", 100, 7, 0)
    stamp = time.time()
    second = write_snapshot(atoms, tmp_path / "snapshots", 200, 5, 123, stamp=stamp, earlier_snapshots_s=first)
    back = read_atoms(tmp_path / "snapshots" / "step-000200.csv")
    np.testing.assert_allclose(back.positions, atoms.positions)
    lines = (tmp_path / "snapshots" / "times.csv").read_text().splitlines()
    assert [line.split(",")[0] for line in lines] == ["100", "200"] and ",5,123," in lines[1]
    assert float(lines[1].split(",")[1]) == pytest.approx(stamp, abs=1e-3)
    # A benchmark reads each step's time less what the earlier snapshots cost the run, and the
    # whole cost for a time after the last (the snapshots are the probe, not the method).
    rows, total = read_snapshot_times(tmp_path / "snapshots")
    assert [r[0] for r in rows] == [100, 200] and rows[1][2:] == (5, 123)
    assert rows[1][1] == pytest.approx(stamp - first, abs=2e-3)
    assert total == pytest.approx(first + second, abs=2e-3) and 0 < first < 10


def test_snapshots_hold_what_the_run_would_report_as_atoms(tmp_path):
    # A 3 x 3 x 3 lattice of 2.5 Å (every atom has neighbours within twice the bond), one blob
    # 30 Å out in vacuum (no neighbour: outside the support) and one lattice site beyond the
    # field of view: the snapshot holds the 26 others, as atoms.xyz would.
    grid = np.stack(np.meshgrid(*[np.arange(3) * 2.5] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    positions = np.vstack([grid, [[30.0, 30.0, 30.0]]])
    atoms = AtomSet(positions, sigmas=np.full(28, 0.6), amplitudes=np.ones(28))
    in_field = np.ones(28, dtype=bool)
    in_field[0] = False
    write_snapshot(atoms, tmp_path / "snapshots", 100, 28, 0, in_field)
    back = read_atoms(tmp_path / "snapshots" / "step-000100.csv")
    np.testing.assert_allclose(back.positions, grid[1:])


def _precision(noise):
    return np.full((4, 3), 0.1), 7.0  # 0.17 Å in 3D


def test_each_check_reports_positions_set_and_scatter_apart():
    """The positions can settle while the set churns (a Gaussian of four goes each check): the
    check is not settled, but says positions_settled and churning.  Removals count by the atoms
    they hold: a fragment of a tenth of an atom removed is within a tolerance of 0.25 atoms,
    a whole atom is not.  Positions that only scatter about fixed places read scatter_only,
    positions that travel do not, and each check's drift per interval says by how much."""
    x = torch.arange(6.0)[:, None] * torch.tensor([0.03, 0.0, 0.0])  # 3 Å apart, 1 Å = 0.01
    check = ConvergenceCheck(warmup_length=0, refine_every=1, changed_fraction=0.05, match_distance=0.007)
    for step, n in enumerate((6, 5, 4), start=1):
        settled = check.update(step, x[:n], 0.01, lambda noise: (np.full((n, 3), 0.1), 7.0))
    assert not settled and check.positions_settled == 2 and check.churning == 2
    check.restart(x[:4])
    assert check.positions_settled == check.churning == 0 and not check.update(4, x[:4], 0.01, _precision)
    weighted = ConvergenceCheck(warmup_length=0, refine_every=1, changed_fraction=0.25 / 4, match_distance=0.007)
    worth = torch.tensor([1.0, 1.0, 1.0, 0.1])
    weighted.update(1, x[:4], 0.01, _precision, worth)
    weighted.update(2, x[:3], 0.01, _precision, worth[:3])  # the fragment went
    assert weighted.changed == pytest.approx(0.1) and weighted.churning == 0
    weighted.update(3, x[:2], 0.01, _precision, worth[:2])  # an atom went
    assert weighted.changed == pytest.approx(1.0) and weighted.churning == 1
    # what a run stopped at its limit says of the last check
    assert "the set changed by 1 atoms' worth (0.19 tolerated)" in weighted.summary()
    fresh = ConvergenceCheck(warmup_length=0, refine_every=1)
    assert fresh.summary() == "no two checks of the atoms to compare yet"

    rng = np.random.default_rng(0)
    many = torch.as_tensor(rng.uniform(-0.5, 0.5, (400, 3)))  # spread wider than the match distance
    precision = lambda noise: (np.full((400, 3), 0.1), 7.0)  # noqa: E731
    scatter = ConvergenceCheck(warmup_length=0, refine_every=1, match_distance=0.007)
    travel = ConvergenceCheck(warmup_length=0, refine_every=1, match_distance=0.007)
    for step in range(1, 4):
        # 0.1 Å per axis about fixed places
        scatter.update(step, many + torch.as_tensor(rng.normal(0, 0.001, (400, 3))), 0.01, precision)
        # and 0.2 Å per axis a check
        travel.update(step, many + step * 0.002 + torch.as_tensor(rng.normal(0, 0.001, (400, 3))), 0.01, precision)
    assert scatter.scatter_only and not travel.scatter_only
    # The drift per interval with the scatter taken out: 0.2 Å per axis a check is 0.35 Å in 3D;
    # scatter alone reads near zero (its estimate's spread over 400 atoms: about 0.03 Å).
    assert travel.drift_A == pytest.approx(0.2 * np.sqrt(3), rel=0.1) and scatter.drift_A < 0.06
    assert travel.precision_A == pytest.approx(0.1 * np.sqrt(3)) and travel.step_A == pytest.approx(
        np.sqrt(3 * (0.2**2 + 2 * 0.1**2)), rel=0.1
    )
    assert "drifting 0.3" in travel.summary() and "precision of 0.173 Å" in travel.summary()


def test_gaussians_beyond_the_reported_field_neither_churn_nor_widen_the_tolerance():
    """Four atoms in the field and four Gaussians beyond it (worth zero: a film's material seen
    only in tilted views).  Those beyond it coming and going leave the set settled; one atom in
    the field gone is one of four (changed_fraction 0.2 tolerates 0.8 of an atom's worth, not
    the 1.6 eight Gaussians would), so the set has not settled."""

    def precision(noise):
        return np.full((8, 3), 0.1), 7.0

    inner = torch.arange(4.0)[:, None] * torch.tensor([0.03, 0.0, 0.0])
    outer = inner + torch.tensor([0.0, 0.5, 0.0])
    both = torch.cat([inner, outer])
    worth = torch.tensor([1.0] * 4 + [0.0] * 4)
    check = ConvergenceCheck(warmup_length=0, refine_every=1, changed_fraction=0.2, match_distance=0.007)
    assert not check.update(1, both, 0.01, precision, worth)
    assert not check.update(2, inner, 0.01, precision, worth[:4])  # those beyond the field all went
    assert check.changed == 0.0
    assert check.update(3, both, 0.01, precision, worth)  # and came back: settled twice
    assert not check.update(4, torch.cat([inner[:3], outer]), 0.01, precision, worth[1:])
    assert check.changed == pytest.approx(1.0) and check.tolerated == pytest.approx(0.8)


def test_a_gaussian_the_data_would_not_prove_neither_churns_nor_a_proven_one_is_forgiven():
    """Four atoms and a fragment.  The precision reads an amplitude level of 1 (its third value);
    the atoms' existence is 20 noise deviations, the fragment's 2, below the proof level of five
    Gaussians (2.88).  The fragment pruned and born again leaves the set settled; the same
    Gaussian at 5 deviations is an atom the data would prove, and its going is a change."""

    def precision(noise):
        return np.full((5, 3), 0.1), 7.0, 1.0

    atoms = torch.arange(4.0)[:, None] * torch.tensor([0.03, 0.0, 0.0])
    both = torch.cat([atoms, torch.tensor([[0.0, 0.05, 0.0]])])
    worth = torch.tensor([1.0] * 4 + [0.3])
    for existence, settles in ((2.0, True), (5.0, False)):
        z = np.array([20.0] * 4 + [existence])
        check = ConvergenceCheck(warmup_length=0, refine_every=1, changed_fraction=0.05, match_distance=0.007)
        assert not check.update(1, both, 0.01, precision, worth, existence=z)
        check.update(2, atoms, 0.01, precision, worth[:4], existence=z[:4])
        assert check.update(3, both, 0.01, precision, worth, existence=z) is settles
        assert check.changed == pytest.approx(0.0 if settles else 0.3)


def test_the_existence_significance_is_the_peak_over_its_cramer_rao_deviation():
    """A Gaussian of width 0.5 Å and peak 1 per Å seen in 40 views of 0.25 Å pixels under white
    noise of 0.1: the information of its peak summed over the pixels of one view (float64,
    a 20 Å square) times 40 gives the deviation; an L1 fit's is sqrt(pi / 2) larger."""
    from gaussian_atoms_method.atoms.uncertainty import existence_significance

    sigma, q, p, s, views = 0.5, 1.0, 0.25, 0.1, 40
    peak = q * sigma * np.sqrt(2 * np.pi)
    x = (np.arange(-40, 40) + 0.5) * p
    image = np.exp(-(x[:, None] ** 2 + x[None, :] ** 2) / (2 * sigma**2))  # the image per unit peak
    expected = peak * np.sqrt(views * (image**2).sum()) / s
    l2 = existence_significance(np.array([sigma]), np.array([q]), views, p, s, "l2")[0]
    l1 = existence_significance(np.array([sigma]), np.array([q]), views, p, s, "l1")[0]
    assert l2 == pytest.approx(expected, rel=1e-6) and l1 == pytest.approx(l2 / np.sqrt(np.pi / 2))


def test_the_places_gathered_from_the_unmatched_are_those_of_the_whole_graph():
    """places_changed reads only the places reached from an unmatched Gaussian; on random sets
    (moved, pruned, born, some unmoved to the bit) it gives what the components of the whole
    closeness graph give."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    def whole_graph(previous, previous_worth, now, now_worth, matched, within):
        unmatched = np.ones(len(previous) + len(now), dtype=bool)
        unmatched[matched[0]] = False
        unmatched[len(previous) + matched[1]] = False
        pairs = cKDTree(previous).sparse_distance_matrix(cKDTree(now), within, output_type="coo_matrix")
        n = len(previous) + len(now)
        graph = coo_matrix((np.ones(pairs.nnz), (pairs.row, len(previous) + pairs.col)), shape=(n, n))
        _, place = connected_components(graph, directed=False)
        change = np.bincount(place, weights=np.concatenate([-previous_worth, now_worth]))
        return float(np.abs(change[np.unique(place[unmatched])]).sum())

    rng = np.random.default_rng(3)
    for trial in range(60):
        previous = rng.uniform(0.0, 10.0, (int(rng.integers(2, 300)), 3))
        now = previous + rng.normal(0.0, [0.01, 0.2, 0.6][trial % 3], previous.shape)
        now[: len(now) // 4] = previous[: len(now) // 4]  # unmoved
        now = np.concatenate([now[rng.random(len(now)) > 0.1], rng.uniform(0.0, 10.0, (5, 3))])
        worth = rng.uniform(0.0, 2.0, len(previous)), rng.uniform(0.0, 2.0, len(now))
        matched = mutual_nearest(previous, now, 0.7)
        within = [0.7, 1.9][trial % 2]
        expected = whole_graph(previous, worth[0], now, worth[1], matched, within)
        assert places_changed(previous, worth[0], now, worth[1], matched, within) == pytest.approx(expected, abs=1e-9)


def test_a_merge_across_the_fields_edge_keeps_its_places_worth():
    """Four atoms in the field and, 1.9 Å from the last, a Gaussian of 0.7 atoms just beyond the
    field (worth zero to the count): joined into one of 1.4 inside the field, the place kept its
    worth, and the set has not changed.  Counted by the field alone the merge would read as 0.7
    of an atom added, against 0.2 tolerated."""

    def precision(noise):
        return np.full((5, 3), 0.1), 7.0

    inner = torch.arange(4.0)[:, None] * torch.tensor([0.03, 0.0, 0.0])  # 3 Å apart, 1 Å = 0.01
    edge = torch.tensor([[0.109, 0.0, 0.0]])  # 1.9 Å beyond the last atom
    before = torch.cat([inner, edge])
    after = torch.cat([inner[:3], (inner[3:] + edge) / 2])
    worth, beyond = torch.tensor([1.0, 1.0, 1.0, 0.7, 0.0]), torch.tensor([0.0, 0.0, 0.0, 0.0, 0.7])
    merged_worth = torch.tensor([1.0, 1.0, 1.0, 1.4])
    for carried, changed in ((True, 0.0), (False, 0.7)):
        check = ConvergenceCheck(warmup_length=0, refine_every=1, changed_fraction=0.05, match_distance=0.007)
        check.update(1, before, 0.01, precision, worth, 0.0187, beyond=beyond if carried else None)
        check.update(2, after, 0.01, precision, merged_worth, 0.0187, beyond=torch.zeros(4) if carried else None)
        assert check.changed == pytest.approx(changed) and check.tolerated == pytest.approx(0.2)
