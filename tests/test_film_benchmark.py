"""The Ta film benchmark: its geometry and its scoring (../shared/data/ta_film)."""

from pathlib import Path

import numpy as np
import pytest

from gaussian_atoms_method.harness.film_benchmark import (
    area_geometry,
    model_in_area_A,
    prepare_area,
    score_area,
    scored_region,
)

DATA = Path("../shared/data/ta_film")
pytestmark = pytest.mark.skipif(not (DATA / "alignPara.mat").is_file(), reason="needs ../shared/data/ta_film")


def test_the_model_scores_itself_perfectly_and_a_shift_is_taken_out():
    """The authors' model as the prediction: every scored atom found, none extra, 0 pm; shifted by
    0.3 Å it is aligned back (the iterated global shift) to the same; with a tenth of its atoms
    removed and as many added 1.6 Å off, found and extra move by that tenth."""
    _, half = area_geometry(DATA, 23)
    model = model_in_area_A(DATA, 23)
    shape = (151, 77)
    perfect = score_area(model, model, shape, tuple(half[:2]))
    assert perfect["found"] == 1.0 and perfect["extra_per_model_atom"] == 0.0 and perfect["rmsd_pm"] < 1e-9
    assert 700 < perfect["n_model"] < 900  # sub-area 23's interior
    shifted = score_area(model + [0.3, -0.2, 0.1], model, shape, tuple(half[:2]))
    assert shifted["found"] == 1.0 and shifted["rmsd_pm"] < 1e-6
    np.testing.assert_allclose(shifted["shift_A"], [-0.3, 0.2, -0.1], atol=1e-9)
    box, inside = scored_region(model, shape, tuple(half[:2]))
    rng = np.random.default_rng(0)
    drop = rng.choice(np.flatnonzero(inside), int(0.1 * inside.sum()), replace=False)
    direction = rng.normal(size=(len(drop), 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    changed = np.concatenate([np.delete(model, drop, axis=0), model[drop] + 1.6 * direction])
    scores = score_area(changed, model, shape, tuple(half[:2]))
    assert scores["found"] == pytest.approx(0.9, abs=0.01)
    # a few of the moved ones leave the scored box
    assert scores["extra_per_model_atom"] == pytest.approx(0.1, abs=0.02)


def test_a_sub_area_past_the_films_edge_scores_nothing_and_says_so(capsys):
    """Strip 1's sub-area 16 holds no atom of the authors' model in its interior (the film ends
    there): its score has no model atom, no found fraction and no extra per model atom, and the
    benchmark's line says nothing was scored instead of failing."""
    from gaussian_atoms_method.harness.film_benchmark import FilmBenchmark

    _, half = area_geometry(DATA, 16)
    model = model_in_area_A(DATA, 16)
    reported = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    scores = score_area(reported, model, (131, 61), tuple(half[:2]))
    assert scores["n_model"] == 0 and scores["n_pred"] == 0
    assert np.isnan(scores["found"]) and np.isnan(scores["extra_per_model_atom"])
    FilmBenchmark(DATA, Path("unused")).say(scores | {"area": 16, "seconds": 40.0, "n_atoms_reported": 2})
    assert capsys.readouterr().out.strip() == (
        "Ta film area 16: no atom of the model in its interior, nothing scored (2 atoms reported), 40 s"
    )


def test_a_sub_area_is_written_as_a_tilt_series(tmp_path):
    """Sub-area 8: 46 views of 131 x 61 pixels, the tilt centre at CropHalf, angles -63 to +56."""
    from dataparsers.tilt_series_format import load_tilt_series

    series = load_tilt_series(prepare_area(DATA, tmp_path, 8))
    assert series.projections.shape == (46, 131, 61)
    assert series.angles_deg.min() == pytest.approx(-63.0, abs=0.01) and series.angles_deg.max() == pytest.approx(
        55.9, abs=0.01
    )
    assert tuple(series.centre_px) == (65.0, 30.0)


def test_the_model_as_a_start_is_the_part_the_detector_sees_on_the_data_frame(tmp_path):
    """``--start-from-model``: every scored model atom is in the start, the film's atoms no tilt
    brings onto the detector are not, and the model's frame is the data's: the shift that takes
    the views' own back-projection peaks onto the model is a small part of a voxel (0.3216 Å;
    the frame one voxel off, as the data's README once gave it, put it at 0.3-1.0 Å), and the
    scorer's own shift of the start undoes it."""
    from gaussian_atoms_method.atoms.atom_set import read_atoms
    from gaussian_atoms_method.harness.film_benchmark import write_model_start

    area_dir = prepare_area(DATA, tmp_path, 8)
    start = read_atoms(write_model_start(DATA, area_dir, 8)).positions
    model = model_in_area_A(DATA, 8)
    _, half = area_geometry(DATA, 8)
    scores = score_area(start, model, (131, 61), tuple(half[:2]))
    assert scores["found"] == 1.0 and scores["rmsd_pm"] < 1e-6
    assert np.linalg.norm(scores["shift_A"]) < 0.5 * 0.3216
    assert len(start) < 0.5 * len(model)  # the film goes on far beyond this sub-area's reach


def test_the_models_frame_puts_a_full_volume_voxel_on_its_sub_volume_index(monkeypatch):
    """The authors' model is ``(1-based full-volume voxel - [201, 176, 171]) * 0.3216`` Å and their
    stitching puts a sub-volume's 0-based index ``i`` at the full volume's 1-based
    ``CropCen - CropHalf + i``: a model atom on full voxel ``CropCen - CropHalf + i`` sits at
    ``(i - CropHalf) * 0.3216`` Å in the sub-area's centred frame, on every axis."""
    from gaussian_atoms_method.harness import film_benchmark
    from gaussian_atoms_method.harness.film_benchmark import FULL_VOLUME_CENTRE_VOX, PIXEL_SIZE_A

    cen, half = area_geometry(DATA, 23)
    index = np.array([[0.0, 0.0, 0.0], [17.0, 5.0, 40.0]])
    model = ((cen - half + index) - FULL_VOLUME_CENTRE_VOX) * PIXEL_SIZE_A
    original = film_benchmark._mat
    monkeypatch.setattr(film_benchmark, "_mat", lambda path, name: model.T if name == "model" else original(path, name))
    np.testing.assert_allclose(model_in_area_A(DATA, 23), (index - half) * PIXEL_SIZE_A, atol=1e-12)


def test_an_extra_atom_beside_one_miss_names_it():
    """Three model atoms, two missed: an extra atom 1 Å from one miss is paired with it, one
    between both misses counts two and names none, one far from both counts none."""
    from gaussian_atoms_method.harness.film_benchmark import missed_nearby

    model = np.array([[0.0, 0.0, 0.0], [2.4, 0.0, 0.0], [9.0, 0.0, 0.0]])
    pred = np.array([[0.0, 0.0, 1.0], [1.2, 0.0, 0.0], [5.0, 5.0, 5.0]])
    count, partner = missed_nearby(pred, model, np.array([0, 1]), np.array([0, 1, 2]), 1.5)
    np.testing.assert_array_equal(count, [1, 2, 0])
    np.testing.assert_array_equal(partner, [0, -1, -1])
    count, partner = missed_nearby(pred, model, np.array([], dtype=np.int64), np.array([0]), 1.5)
    np.testing.assert_array_equal(count, [0])
    np.testing.assert_array_equal(partner, [-1])


def test_the_models_pairs_closer_than_the_hard_core_cannot_all_be_reported_where_they_lie():
    """Two atoms closer than tantalum's hard core (1.87 Å) cannot both be reported where they lie
    (``most_apart``'s cases: tests/test_hard_core.py); only the scored region's atoms count.  The
    authors' model holds three such pairs (1.53-1.86 Å) in sub-area 23's scored region: 780 of its
    783 atoms at most."""
    from gaussian_atoms_method.atoms.hard_core import hard_core_from_species
    from gaussian_atoms_method.harness.film_benchmark import most_reportable

    core = hard_core_from_species("Ta")
    pair_and_far = np.array([[0.0, 0, 0], [1.5, 0, 0], [20.0, 0, 0], [30.0, 0, 0]])
    assert most_reportable(pair_and_far, np.ones(4, bool), core) == 3
    assert most_reportable(pair_and_far, np.array([True, False, True, True]), core) == 3  # one outside
    _, half = area_geometry(DATA, 23)
    model = model_in_area_A(DATA, 23)
    _, inside = scored_region(model, (151, 77), tuple(half[:2]))
    assert (int(inside.sum()), most_reportable(model, inside, core)) == (783, 780)


def test_a_replicas_truth_is_the_model_less_the_pairs_no_specimen_holds(tmp_path):
    """``benchmark-film --replica`` scores against the replica's own truth: the authors' model with
    one atom of each pair closer than the shortest bond tantalum can form (2.11 Å) set aside (412 of
    the whole film's 8,284 atoms), the rest where the model puts them; the real views are scored
    against the model."""
    from scipy.spatial import cKDTree

    from dataparsers.tilt_series_format import load_tilt_series
    from gaussian_atoms_method.atoms.hard_core import close_pairs, shortest_bond_from_species
    from gaussian_atoms_method.harness.film_benchmark import FilmBenchmark

    bond = shortest_bond_from_species("Ta")
    model = model_in_area_A(DATA, 8)
    bench = FilmBenchmark(DATA, tmp_path, areas=(8,), replica=True)
    truth = bench.truth_A(8, load_tilt_series(bench.prepare(8)))
    assert len(close_pairs(truth, bond)) == 0 and len(truth) == len(model) - 412
    assert cKDTree(model).query(truth)[0].max() < 1e-4  # each truth atom a model atom, where it lies
    np.testing.assert_array_equal(FilmBenchmark(DATA, tmp_path).truth_A(8, None), model)


def test_neighbouring_replicas_sit_in_the_films_frame_where_their_truths_coincide(tmp_path):
    """``benchmark-film --replica`` fits each replica with its strip neighbours' as a film
    (harness/film_replica.py): placed by their crops' centres, two neighbouring replicas' truths
    (each the model in its own sub-area's frame) put every atom of their common interior on one
    place (to float32 rounding of the written files), so the overlap judges their fits on shared
    atoms.  The neighbours of a strip's end are its own strip's only."""
    from scipy.spatial import cKDTree

    from dataparsers.tilt_series_format import load_tilt_series
    from gaussian_atoms_method.atoms.atom_set import read_atoms
    from gaussian_atoms_method.film.stitch import Reports
    from gaussian_atoms_method.harness.film_replica import neighbourhood, replica_subareas

    assert neighbourhood([16, 17]) == [15, 16, 17, 18]
    with pytest.raises(ValueError, match="--areas: no published sub-area 30"):
        neighbourhood([30])
    placed = []
    for sub in replica_subareas(DATA, tmp_path, [22, 23]):
        series = load_tilt_series(sub.data)
        truth = read_atoms(series.truth_path).positions - np.asarray(series.origin_A) + np.asarray(sub.offset_A)
        placed.append(Reports(sub.name, truth, sub.interior_A))
    a, b = placed
    shared = a.positions[a.inside(a.positions) & b.inside(a.positions)]
    assert len(shared) > 300
    assert cKDTree(b.positions).query(shared)[0].max() < 1e-3
