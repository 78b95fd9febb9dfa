"""A film wider than the field, fitted in overlapping sub-areas on Ray and joined
(gaussian_atoms_method/film/)."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from gaussian_atoms_method.atoms.atom_set import read_atoms
from gaussian_atoms_method.film.stitch import Reports, confirm, join_reports, pair_agreement

HARD_CORE_A = 2.2


def _reports(rng, truth, offsets_x, width=20.0, jitter_A=0.03, edge_A=2.0):
    """Sub-areas ``width`` Å across at ``offsets_x``, each reporting the true atoms inside it
    with ``jitter_A`` of noise."""
    out = []
    for i, x0 in enumerate(offsets_x):
        lo, hi = np.array([x0 - width / 2, -50.0]), np.array([x0 + width / 2, 50.0])
        seen = truth[np.all((truth[:, :2] >= lo) & (truth[:, :2] <= hi), axis=1)]
        out.append(
            Reports(f"s{i}", seen + rng.normal(scale=jitter_A, size=seen.shape), np.stack([lo + edge_A, hi - edge_A]))
        )
    return out


def _lattice(nx=30, ny=4, spacing=2.8):
    x, y = np.meshgrid(np.arange(nx) * spacing, np.arange(ny) * spacing, indexing="ij")
    return np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])


def test_overlapping_reports_of_one_atom_become_one_atom_at_their_mean():
    """Seven sub-areas every 3 Å over a lattice 2.8 Å apart (the hard core 2.2 Å): each atom
    is found once, at the mean of its reports (the reports' 3 pm scatter shrinks by the square
    root of their number), with found_in equal to covered_by."""
    rng = np.random.default_rng(0)
    truth = _lattice()
    reports = _reports(rng, truth, offsets_x=np.arange(10.0, 70.0, 3.0))
    film = join_reports(reports, HARD_CORE_A)
    inner = np.all((truth[:, :1] > 20) & (truth[:, :1] < 60), axis=1)
    from gaussian_atoms_method.atoms.matching import score_atoms

    scores = score_atoms(film.positions, truth[inner])
    assert scores["tpr"] == 1.0 and scores["rmsd_pm"] < 3.0
    from scipy.spatial import cKDTree

    assert len(cKDTree(film.positions).query_pairs(HARD_CORE_A)) == 0  # none doubled
    # found by every fit that covers it, but where a report's scatter crossed an interior's edge
    edges = np.concatenate([r.interior_A[:, 0] for r in reports])
    clear = np.min(np.abs(film.positions[:, :1] - edges[None, :]), axis=1) > 0.2
    assert np.all(film.found_in[clear] == film.covered_by[clear])
    # each atom's reports spread as the fits scatter (3 pm per axis; the median over atoms of a
    # standard deviation of ~7 reports: within 20%)
    several = film.found_in[clear] > 2
    assert np.allclose(np.median(film.spread_A[clear][several], axis=0), 0.03, rtol=0.2)
    assert np.all(np.isnan(film.spread_A[film.found_in == 1]))
    # no fit made an artefact: the recurrence rates do not separate, the overlap confirms nothing
    # and every joined atom is reported
    assert not film.separated and not film.confirmed.any() and film.reported.all()


def test_a_joined_atom_is_trusted_where_most_of_the_fits_that_found_it_trust_it():
    """Seven sub-areas over a lattice; each fit trusts each of its atoms but one in five, drawn
    apart, and one column of atoms no fit trusts.  trusted_in counts the finders that trust each
    joined atom (one report per fit), and the film trusts an atom where more than half of its
    finders do: every atom of the untrusted column is left out, and an atom some fits doubt is
    trusted exactly where the fits that trust it outnumber those that do not."""
    rng = np.random.default_rng(5)
    truth = _lattice()
    reports = _reports(rng, truth, offsets_x=np.arange(10.0, 70.0, 3.0))
    doubted_x = 14 * 2.8
    for r in reports:
        column = np.abs(r.positions[:, 0] - doubted_x) < 0.5
        r.trusted = (rng.uniform(size=len(r.positions)) > 0.2) & ~column
    film = join_reports(reports, HARD_CORE_A)
    expected = np.zeros(len(film.positions), np.int64)
    tree_points = [(r, r.inside(r.positions)) for r in reports]
    for r, inside in tree_points:
        for p, trusted in zip(r.positions[inside], r.trusted[inside]):
            expected[np.argmin(np.linalg.norm(film.positions - p, axis=1))] += trusted
    assert np.array_equal(film.trusted_in, expected)
    assert np.array_equal(film.trusted, film.reported & (2 * expected > film.found_in))
    column = np.abs(film.positions[:, 0] - doubted_x) < 0.5
    assert column.any() and not film.trusted[column].any() and film.trusted[~column].mean() > 0.8
    # fits that do not say which atoms they trust: the film does not either
    for r in reports:
        r.trusted = None
    assert join_reports(reports, HARD_CORE_A).trusted is None


def test_overlapping_fits_are_judged_on_the_atoms_both_see_each_way():
    """Three sub-areas 20 Å across every 5 Å over a lattice: neighbours share a common interior,
    the first and third less.  Fits that report the same atoms agree 1.0 both ways; one fit that
    misses two atoms of the common interior and invents one there is named: the other sees 2 of
    its atoms missing, it sees 1 of its own unreported; atoms outside the common interior (where
    only one fit sees them) count for neither."""
    rng = np.random.default_rng(1)
    truth = _lattice(nx=20)
    a, b, c = _reports(rng, truth, offsets_x=[15.0, 20.0, 25.0])
    pairs = {(p.a, p.b): p for p in pair_agreement([a, b, c], HARD_CORE_A)}
    assert set(pairs) == {("s0", "s1"), ("s0", "s2"), ("s1", "s2")}
    assert all(p.agree_a == 1.0 and p.agree_b == 1.0 for p in pairs.values())
    common = pairs[("s0", "s1")]
    lo, hi = np.maximum(a.interior_A[0], b.interior_A[0]) + 1.1, np.minimum(a.interior_A[1], b.interior_A[1]) - 1.1
    shared = np.flatnonzero(np.all((b.positions[:, :2] > lo) & (b.positions[:, :2] < hi), axis=1))
    assert common.n_a == common.n_b == len(shared) > 10
    invented = b.positions[shared[0]] + [1.4, 1.4, 0.0]  # between lattice sites, 1.98 Å from each
    b = Reports("s1", np.r_[np.delete(b.positions, shared[1:3], axis=0), [invented]], b.interior_A)
    p = pair_agreement([a, b], HARD_CORE_A)[0]
    assert p.n_a == len(shared) and p.agree_a == pytest.approx((len(shared) - 2) / len(shared))
    assert p.n_b == len(shared) - 1 and p.agree_b == pytest.approx((len(shared) - 2) / (len(shared) - 1))
    assert p.both_ways == min(p.agree_a, p.agree_b)
    # counted over the atoms a run trusts (not the invented one), matched against all the other's
    trusted = np.arange(len(b.positions)) < len(b.positions) - 1
    t = pair_agreement([a, b], HARD_CORE_A, [np.ones(len(a.positions), bool), trusted])[0]
    assert t.n_b == len(shared) - 2 and t.agree_b == 1.0 and t.agree_a == p.agree_a


def test_overlapping_fits_judge_each_others_positions_against_their_stated_precisions():
    """Two fits of one lattice, each place scattered by 3 pm per axis: stated as 3 pm, their
    differences (3 pm times sqrt 2 per axis) lie within the combined 95% interval for 0.95 of the
    shared atoms (the binomial's 2.6 standard deviations over ~500 pairs: 0.025); stated as half
    that, for P(|z| < 0.98) = 0.67.  A shift of one crop's whole frame is the pair's offset (the
    crops' registration), not any atom's scatter; without precisions nothing is judged."""
    rng = np.random.default_rng(2)
    truth = _lattice(nx=60, ny=16)
    a, b = _reports(rng, truth, offsets_x=[70.0, 90.0], width=120.0, jitter_A=0.03)
    frame = np.array([0.10, -0.05, 0.02])
    for stated, expected in ((0.03, 0.95), (0.015, 0.67)):
        sa, sb = (
            Reports(r.name, r.positions + shift, r.interior_A, np.full((len(r.positions), 3), stated))
            for r, shift in ((a, 0.0), (b, frame))
        )
        p = pair_agreement([sa, sb], HARD_CORE_A)[0]
        assert p.n_pairs == p.n_a > 400 and p.agree_a == 1.0
        assert np.allclose(p.offset_A, frame, atol=0.005)  # the mean of n differences: 4.2 pm / sqrt(n)
        assert np.allclose(p.scatter_pm, 3 * np.sqrt(2), rtol=0.1)
        assert np.allclose(p.intervals_hold, expected, atol=0.06)
        assert "within their stated 95% intervals" in p.position_words()
    plain = pair_agreement([a, b], HARD_CORE_A)[0]
    assert np.all(np.isnan(plain.intervals_hold)) and plain.position_words() == ""


def test_each_sub_area_keeps_the_registration_its_overlapping_neighbours_agree_with():
    """Four sub-areas along a lattice, each fitted twice: without registration every report is
    8 pm off; with it three are 1 pm off and the third's registration failed (its atoms 30 pm off
    along the beam, a drift each view shares).  Started from all registered, the third alone goes
    back: the film is registered where it helps and nowhere it harms; with no overlap nothing is
    decided."""
    from gaussian_atoms_method.film.registration import registration_by_overlap

    rng = np.random.default_rng(3)
    truth = _lattice(nx=40)
    offsets = [20.0, 35.0, 50.0, 65.0]
    plain = _reports(rng, truth, offsets, width=30.0, jitter_A=0.08)
    registered = _reports(rng, truth, offsets, width=30.0, jitter_A=0.01)
    failed = registered[2]
    registered[2] = Reports(
        failed.name,
        failed.positions + [0.0, 0.0, 0.3] + rng.normal(scale=0.1, size=failed.positions.shape),
        failed.interior_A,
    )
    for r in (*plain, *registered):
        r.position_std_A = np.full((len(r.positions), 3), 0.05)
    choice = registration_by_overlap({"without_registration": plain, "with_registration": registered}, HARD_CORE_A)
    assert choice["decided"] and choice["registered"] == ["s0", "s1", "s3"]
    assert choice["median_apart_pm"]["chosen"] < choice["median_apart_pm"]["none"]
    assert choice["median_agree_both_ways"]["chosen"] >= choice["median_agree_both_ways"]["none"]
    alone = registration_by_overlap(
        {"without_registration": plain[:1], "with_registration": registered[:1]}, HARD_CORE_A
    )
    assert not alone["decided"] and alone["registered"] == []


def test_a_registration_that_loses_one_atom_of_hundreds_is_still_kept_where_it_brings_neighbours_together():
    """Three sub-areas, registered 1 pm off against 8 pm without; the last one's registered fit
    misses one atom of its common interiors' ~100 (a fit's rare event, within the count's Poisson
    scatter): it is still registered.  Missing a tenth of them is fewer beyond counting: it goes
    back."""
    from gaussian_atoms_method.film.registration import registration_by_overlap

    truth = _lattice(nx=40)
    offsets = [20.0, 35.0, 50.0]
    for dropped, kept in ((1, ["s0", "s1", "s2"]), (12, ["s0", "s1"])):
        rng = np.random.default_rng(4)
        plain = _reports(rng, truth, offsets, width=30.0, jitter_A=0.08)
        registered = _reports(rng, truth, offsets, width=30.0, jitter_A=0.01)
        last = registered[2]
        inside = np.flatnonzero(np.all(last.positions[:, :2] > last.interior_A[0], axis=1))
        registered[2] = Reports(last.name, np.delete(last.positions, inside[:dropped], axis=0), last.interior_A)
        for r in (*plain, *registered):
            r.position_std_A = np.full((len(r.positions), 3), 0.05)
        choice = registration_by_overlap({"without_registration": plain, "with_registration": registered}, HARD_CORE_A)
        assert choice["registered"] == kept


def test_an_artefact_of_one_fit_is_a_non_atom():
    """Real atoms found by 6-7 of 7 covering fits, artefacts each in one fit: the mixture reads
    the two rates and reports the artefacts as non-atoms."""
    rng = np.random.default_rng(1)
    n = np.full(400, 7)
    k = np.r_[rng.binomial(7, 0.95, 300), rng.binomial(7, 0.1, 100).clip(min=1)]
    confirmed, real, artefact = confirm(k, n)
    assert confirmed[:300].mean() > 0.98 and confirmed[300:].mean() < 0.05
    assert real > 0.9 and artefact < 0.25


def _fit_on_disk(directory, atoms, non_atoms=None):
    """A sub-area's fit as a run writes it: ``atoms.xyz`` and, where given, ``non_atoms.xyz``."""
    from gaussian_atoms_method.atoms.atom_set import write_atoms

    directory.mkdir(parents=True)
    write_atoms(atoms, directory / "atoms.xyz")
    if non_atoms is not None:
        write_atoms(non_atoms, directory / "non_atoms.xyz")
    return {"atoms": str(directory / "atoms.xyz")}


def test_a_class_one_fit_kept_and_its_neighbour_set_apart_is_decided_once_for_the_film(tmp_path):
    """Two overlapping sub-areas over one film of 320 atoms (log masses 0 +- 0.05, 0.6 Å wide)
    with 120 light, wide Gaussians (a third of an atom's mass, 0.9 Å) in a layer 8-12 Å above it:
    one fit reported the layer as atoms, the other set it apart.  The film decides once over
    both fits' Gaussians: the layer is a class apart in both, so the two agree on every atom of
    their common interior; a Gaussian within the hard core of a heavier one stays a non-atom,
    as the run holds it; where a fit wrote no non-atoms the film keeps the fits' own atoms."""
    from gaussian_atoms_method.atoms.atom_set import AtomSet
    from gaussian_atoms_method.film.film import film_reports
    from gaussian_atoms_method.film.subareas import SubArea

    rng = np.random.default_rng(3)
    grid = np.stack(np.meshgrid(np.arange(-14.0, 14.0, 2.8), np.arange(-11.0, 11.0, 2.8), [0.0, 2.8, 5.6, 8.4]), -1)
    film = grid.reshape(-1, 3) + rng.normal(0, 0.05, (grid.size // 3, 3))
    layer = np.c_[rng.uniform(-14, 14, 120), rng.uniform(-11, 11, 120), rng.uniform(16, 20, 120)]
    twin = film[len(film) // 2] + [0.0, 0.0, 1.0]  # within the hard core of an atom, lighter
    subareas, records = [], {}
    for i, (x0, reported) in enumerate(((-3.0, True), (3.0, False))):
        sub = SubArea(f"s{i}", tmp_path, (x0, 0.0, 0.0), (101, 121), (50.0, 60.0), 0.2, (10, 4))
        inside = np.abs(np.r_[film, layer, [twin]][:, 0] - x0) <= 10.0
        positions = np.r_[film, layer, [twin]][inside] - [x0, 0.0, 0.0]
        n = len(positions)
        masses = np.exp(np.r_[rng.normal(0, 0.05, len(film)), rng.normal(-1.1, 0.05, len(layer)), [-0.5]])[inside]
        sigmas = np.r_[np.full(len(film), 0.6), np.full(len(layer), 0.9), [0.6]][inside]
        is_atom = np.r_[np.ones(len(film), bool), np.full(len(layer), reported), [False]][inside]
        fit = AtomSet(positions, sigmas, masses / (2 * np.pi * sigmas**2) ** 1.5, position_std_A=np.full((n, 3), 0.02))
        fit.trusted = np.ones(n, np.int64)
        records[sub.name] = _fit_on_disk(tmp_path / sub.name, fit.subset(is_atom), fit.subset(~is_atom))
        subareas.append(sub)
    reports = film_reports(subareas, records, HARD_CORE_A)
    for r in reports:
        assert not (r.positions[:, 2] > 14.0).any()  # the layer: apart in both
        assert np.min(np.linalg.norm(r.positions - twin, axis=1)) > 0.5  # the twin: within the core
    pair = pair_agreement(reports, HARD_CORE_A)[0]
    assert pair.n_a > 50 and pair.agree_a == 1.0 and pair.agree_b == 1.0
    # without non-atoms on disk: each fit's own atoms (the first keeps its layer)
    for sub in subareas:
        (tmp_path / sub.name / "non_atoms.xyz").unlink()
    own = film_reports(subareas, records, HARD_CORE_A)
    assert (own[0].positions[:, 2] > 14.0).any() and not (own[1].positions[:, 2] > 14.0).any()
    assert pair_agreement(own, HARD_CORE_A)[0].agree_a < 1.0  # the first's layer, unseen by the second


def test_reports_farther_apart_than_half_the_hard_core_stay_apart():
    """Two fits reporting points 1.5 Å apart (more than half of a 2.2 Å hard core): two atoms,
    each found in one of the two fits that cover it."""
    inner = np.array([[-10.0, -10.0], [10.0, 10.0]])
    a = Reports("a", np.array([[0.0, 0.0, 0.0]]), inner)
    b = Reports("b", np.array([[1.5, 0.0, 0.0]]), inner)
    film = join_reports([a, b], HARD_CORE_A)
    assert len(film.positions) == 2 and list(film.found_in) == [1, 1] and list(film.covered_by) == [2, 2]


@pytest.fixture(scope="module")
def small_film(tmp_path_factory):
    """A 36 x 14 x 8 Å Pd film (Gaussian potential, 21 tilts) and its series cut into two
    sub-areas 30 Å across, 6 Å apart."""
    from dataparsers.tilt_series_format import TiltSeries
    from gaussian_atoms_method.film.subareas import tile_series
    from gaussian_atoms_method.harness.particles import amorphous_packing
    from gaussian_atoms_method.harness.simulate import simulate_tilt_series

    rng = np.random.default_rng(0)
    atoms = amorphous_packing(0, ("Pd",), 2.5, rng, number_density_per_A3=0.04, box_A=(36.0, 14.0, 8.0))
    angles = np.arange(-60.0, 61.0, 6.0)
    sim = simulate_tilt_series(atoms, angles, potential="gaussian", noise_std=20.0, seed=0)
    series = TiltSeries(sim.projections, angles, 0.25, "y")
    root = tmp_path_factory.mktemp("film")
    h = series.projections.shape[1]
    subareas = tile_series(series, (h - 24, 400), (24, 400), root / "data")
    return atoms, subareas, root


def test_a_film_runs_on_ray_resumes_and_names_a_broken_sub_area(small_film):
    """Two sub-areas as Ray tasks on this machine's local cluster.  One sub-area's projections
    broken: the film fails naming it, after the other finished.  Repaired and run again, only
    the broken one runs (the finished one is read back), and the joined film holds every
    atom of the interiors' union once, at the fits' precision."""
    import ray

    from gaussian_atoms_method.atoms.matching import score_atoms
    from gaussian_atoms_method.film.film import FilmError, reconstruct_film

    truth, subareas, root = small_film
    broken = Path(subareas[1].data) / "projections.npy"
    good = broken.read_bytes()
    broken.write_bytes(b"not an array")
    try:
        with pytest.raises(FilmError, match=subareas[1].name):
            reconstruct_film(
                subareas, root / "out", species="Pd", max_steps=1500, progress=False, registration_by_overlap=False
            )
        first = root / "out" / "runs" / subareas[0].name / "gaussian-atoms" / "run" / "done.json"
        assert first.is_file() and not (root / "out" / "atoms.xyz").exists()
        stamp = first.stat().st_mtime_ns
        broken.write_bytes(good)
        film = reconstruct_film(
            subareas, root / "out", species="Pd", max_steps=1500, progress=False, registration_by_overlap=False
        )
    finally:
        ray.shutdown()
    assert first.stat().st_mtime_ns == stamp  # read back, not run again
    from gaussian_atoms_method.atoms.hard_core import hard_core_from_species

    # the film's species set each fit's hard core, not only the join's
    assert json.loads(first.read_text())["hard_core_A"] == pytest.approx(hard_core_from_species("Pd"))
    reported = film.positions[film.reported]  # two sub-areas: the overlap confirms nothing, every atom is reported
    summary = json.loads((root / "out" / "summary.json").read_text())
    assert not summary["overlap_separates"] and summary["confirmed_by_overlap"] == 0
    union = np.zeros(len(truth), dtype=bool)
    for s in subareas:
        union |= Reports(s.name, truth.positions, s.interior_A).inside(truth.positions)
    # well-separated atoms of the model's own physics: all found and none invented, as the
    # single-series end-to-end test asks; 5 pm is far below the 0.25 Å pixel
    scores = score_atoms(reported, truth.positions[union], radius_A=0.75)
    assert scores["tpr"] >= 0.99 and scores["fp_per_true_atom"] <= 0.01 and scores["rmsd_pm"] < 10.0
    from scipy.spatial import cKDTree

    assert len(cKDTree(reported).query_pairs(2.0)) == 0  # none doubled at the seam
    for name in ("atoms.xyz", "non_atoms.xyz", "atoms.csv", "film.png", "summary.json", "overlaps.csv"):
        assert (root / "out" / name).is_file()
    # the fits say which atoms they trust, and the film which of its own: a majority of the finders
    assert film.trusted is not None and summary["trusted"] == int(film.trusted.sum()) > 0.9 * len(reported)
    table = np.genfromtxt(root / "out" / "atoms.csv", delimiter=",", names=True)
    assert np.array_equal(table["trusted"] > 0, film.trusted) and np.array_equal(table["trusted_in"], film.trusted_in)
    # the two fits of one physics report each other's atoms where both see them
    assert summary["overlap_agreement"]["pairs"] == 1 and summary["overlap_agreement"]["median_both_ways"] >= 0.97
    # and place them alike: per axis within the 10 pm each fit's RMSD is held to above
    assert np.all(np.asarray(summary["overlap_agreement"]["median_scatter_pm"]) < 10.0)
    assert set(read_atoms(root / "out" / "atoms.xyz").species) == {"Pd"}  # the film's one element names them
    # each task's cost, recorded by the task and read back with it: a fit takes time, a worker
    # holds at least torch's own import (hundreds of MB), and CPU tasks have no GPU peak
    tasks = json.loads((root / "out" / "summary.json").read_text())["tasks"]
    assert 0 < tasks["median_fit_s"] <= tasks["max_fit_s"]
    assert tasks["max_worker_rss_GB"] > 0.1 and tasks["max_peak_gpu_GB"] is None
    # and whether each fit converged before its step limit, as its run reported it
    records = [json.loads(f.read_text()) for f in (root / "out" / "runs").glob("*/gaussian-atoms/run/done.json")]
    assert len(records) == 2 and all(isinstance(r["converged"], bool) and 0 < r["steps"] <= 1500 for r in records)
    assert tasks["convergence_known"] == 2 and tasks["converged"] == sum(r["converged"] for r in records)


def test_the_overlap_keeps_per_view_shifts_where_each_crop_is_misregistered_apart(tmp_path):
    """The small film's two sub-areas, each view of each crop shifted apart by 0.5 px RMS (as
    sub-areas registered one by one are): fitted without shifts, the two crops' errors differ and
    their fits place the atoms they share tens of pm apart; with shifts learned both are put
    right, so the overlap keeps the fits with registration (shifts and gains), and the joined film
    is theirs."""
    import ray
    from scipy.ndimage import shift

    from dataparsers.tilt_series_format import TiltSeries
    from gaussian_atoms_method.film.film import reconstruct_film
    from gaussian_atoms_method.film.subareas import tile_series
    from gaussian_atoms_method.harness.particles import amorphous_packing
    from gaussian_atoms_method.harness.simulate import simulate_tilt_series

    rng = np.random.default_rng(0)
    atoms = amorphous_packing(0, ("Pd",), 2.5, rng, number_density_per_A3=0.04, box_A=(36.0, 14.0, 8.0))
    angles = np.arange(-60.0, 61.0, 6.0)
    sim = simulate_tilt_series(atoms, angles, potential="gaussian", noise_std=20.0, seed=0)
    series = TiltSeries(sim.projections, angles, 0.25, "y")
    h = series.projections.shape[1]
    subareas = tile_series(series, (h - 24, 400), (24, 400), tmp_path / "data")
    for sub in subareas:
        path = Path(sub.data) / "projections.npy"
        views = np.load(path)
        moved = [shift(v, rng.normal(scale=0.5, size=2), order=3, mode="nearest") for v in views]
        np.save(path, np.asarray(moved, dtype=views.dtype))
    try:
        film = reconstruct_film(
            subareas, tmp_path / "out", species="Pd", max_steps=1500, progress=False, registration_by_overlap=True
        )
    finally:
        ray.shutdown()
    choice = json.loads((tmp_path / "out" / "registration.json").read_text())
    assert choice["decided"] and set(choice["chosen"].values()) == {"with_registration"}
    apart = choice["median_apart_pm"]
    assert apart["chosen"] == apart["all"] < apart["none"]
    for name in ("without_registration", "with_registration"):
        assert (tmp_path / "out" / "runs" / name / subareas[0].name / "gaussian-atoms" / "run" / "done.json").is_file()
    # the film joined is the kept set's: its one pair's scatter is the one the choice read
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert np.linalg.norm(summary["overlap_agreement"]["median_scatter_pm"]) == pytest.approx(apart["chosen"])
    assert len(film.positions) > 0


@pytest.mark.parametrize(
    "args, named",
    [
        ([], "--published DIR"),
        (["--published", "/nonexistent", "--areas", "1"], "--pixel-size-A"),
        (["--published", "/nonexistent", "--areas", "one", "--pixel-size-A", "0.32"], "--areas"),
        (["--published", "/nonexistent", "--areas", "1", "--pixel-size-A", "0.32"], "/nonexistent/alignPara.mat"),
        (["--series", "/nonexistent"], "/nonexistent"),
        (["--series", "/nonexistent", "--tasks-per-gpu", "0"], "--tasks-per-gpu"),
        (["--series", "/nonexistent", "--max-num-iterations", "0"], "--max-num-iterations"),
        (["--series", "/nonexistent", "--species", "Ta,Xx"], "unknown element 'Xx'"),
        (["--series", "/nonexistent", "--address", "127.0.0.1:1"], "no Ray cluster answers"),
    ],
)
def test_film_input_errors_are_one_line_and_write_nothing(tmp_path, capsys, args, named):
    from gaussian_atoms_method.cli import entrypoint

    out = tmp_path / "film"
    with pytest.raises(SystemExit) as exit_info:
        entrypoint(["film", "--output", str(out), "--device", "cpu", *args])
    err = capsys.readouterr().err.strip()
    assert exit_info.value.code == 2 and len(err.splitlines()) == 1 and named in err, err
    assert not out.exists()


def test_the_film_thickness_is_read_from_the_series():
    """A Pd slab 12 Å thick, tilts -60..60: the back-projected section's half-maximum width is
    the slab's depth, widened by the atoms' own width (0.6 Å blurred, on each face) and the
    missing wedge's stretch, narrowed where the faces' half maximum falls inside the outermost
    atoms: within 15% below the atoms' depth span and half as much again above."""
    from dataparsers.tilt_series_format import TiltSeries
    from gaussian_atoms_method.film.subareas import default_tiling, film_thickness_A
    from gaussian_atoms_method.harness.particles import amorphous_packing
    from gaussian_atoms_method.harness.simulate import simulate_tilt_series

    atoms = amorphous_packing(
        0, ("Pd",), 2.5, np.random.default_rng(0), number_density_per_A3=0.04, box_A=(50.0, 12.0, 12.0)
    )
    angles = np.arange(-60.0, 61.0, 4.0)
    series = TiltSeries(
        simulate_tilt_series(atoms, angles, potential="gaussian", seed=0).projections, angles, 0.25, "y"
    )
    span = np.ptp(atoms.positions[:, 2])
    assert 0.85 * span <= film_thickness_A(series) <= 1.5 * span
    (across, along), (step, _) = default_tiling(series)
    assert along == series.projections.shape[2] and 6 <= across / step <= 8


@pytest.mark.parametrize(
    "options, named",
    [
        ({"tasks_per_gpu": 0}, "tasks_per_gpu"),
        ({"tasks_per_gpu": 1.5}, "tasks_per_gpu"),
        ({"tasks_per_gpu": True}, "tasks_per_gpu"),
        ({"max_steps": 0}, "max_steps"),
        ({"species": "Xx"}, "unknown element 'Xx'"),
        ({}, "subareas: none given"),
        ({"refine_gain": True}, "refine_gain: registration_by_overlap decides it"),
        ({"address": "127.0.0.1:1"}, "no Ray cluster answers"),
        ({"address": "nowhere"}, "expected HOST:PORT"),
    ],
)
def test_reconstruct_film_checks_its_arguments_before_writing(tmp_path, options, named):
    from gaussian_atoms_method.film.film import reconstruct_film

    with pytest.raises(ValueError, match=named):
        reconstruct_film([], tmp_path / "film", **options)
    assert not (tmp_path / "film").exists()


def test_the_tasks_device_follows_the_cluster():
    from gaussian_atoms_method.film.runner import cluster_device

    assert cluster_device("auto", 0, None) == "cpu" and cluster_device("auto", 2.0, None) == "cuda"
    assert cluster_device("cpu", 4.0, None) == "cpu" and cluster_device("cuda", 1.0, "h:1") == "cuda"
    with pytest.raises(ValueError, match="cluster at h:1 has no GPU"):  # its tasks would wait forever
        cluster_device("cuda", 0, "h:1")


@pytest.mark.skipif(torch.cuda.is_available(), reason="a machine without a GPU")
def test_device_cuda_without_a_gpu_is_one_line_and_writes_nothing(tmp_path, capsys):
    from gaussian_atoms_method.cli import entrypoint

    out = tmp_path / "film"
    argv = ["film", "--published", "/nonexistent", "--areas", "1", "--pixel-size-A", "0.32", "--device", "cuda"]
    with pytest.raises(SystemExit) as exit_info:
        entrypoint([*argv, "--output", str(out)])
    err = capsys.readouterr().err.strip()
    assert exit_info.value.code == 2 and len(err.splitlines()) == 1 and "--device cuda" in err, err
    assert not out.exists()


def test_areas_are_read_as_numbers_and_ranges_each_once():
    from gaussian_atoms_method.cli.film_verb import parse_areas

    assert parse_areas("1-3,8") == [1, 2, 3, 8]
    assert parse_areas("8, 8,2-3,3") == [8, 2, 3]  # a sub-area named twice is fitted once
    with pytest.raises(ValueError, match="--areas"):
        parse_areas("1-x")


def test_a_tile_without_an_interior_is_one_line_and_writes_nothing(tmp_path, capsys):
    from dataparsers.tilt_series_format import write_tilt_series
    from gaussian_atoms_method.cli import entrypoint

    series = write_tilt_series(
        tmp_path / "series", np.random.default_rng(0).uniform(1, 2, (3, 40, 40)), [-30.0, 0.0, 30.0], 0.25
    )
    out = tmp_path / "film"
    with pytest.raises(SystemExit) as exit_info:
        entrypoint(
            ["film", "--series", str(series), "--tile-px", "5", "5", "--step-px", "1", "1", "--output", str(out)]
        )
    err = capsys.readouterr().err.strip()
    assert exit_info.value.code == 2 and len(err.splitlines()) == 1 and "leaves no interior" in err, err
    assert not out.exists()


def test_a_sub_area_finished_with_other_settings_is_fitted_again(tmp_path):
    from gaussian_atoms_method.film.runner import finished, fit_settings

    done = tmp_path / "done.json"
    asked = fit_settings({"loss": "huber"}, 3000, "Ta")
    assert finished(done, asked) is None  # not run yet
    done.write_text(json.dumps({"name": "a", "settings": asked}) + "\n")
    assert finished(done, asked)["name"] == "a"  # the same settings: read back
    assert finished(done, fit_settings({"loss": "huber"}, 3000, "")) is None  # another species
    assert finished(done, fit_settings({"loss": "huber"}, 1500, "Ta")) is None  # another step limit
    done.write_text(json.dumps({"name": "a"}) + "\n")  # recorded before the settings were
    assert finished(done, asked) is None
