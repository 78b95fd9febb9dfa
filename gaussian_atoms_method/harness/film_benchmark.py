"""The real-data benchmark: sub-areas of a measured amorphous Ta film (ADF-STEM).

Data (``../shared/data/ta_film``, README there): Y. Yuan et al., "Three-dimensional atomic
packing in amorphous solids with liquid-like structure", Nature Materials 21, 95-102 (2022);
cite it with any number or figure made from these files.  Four sub-areas of a tilt series
(46 tilts, -63 to +56 degrees, 0.3216 Å pixels), denoised and aligned by the authors, and their
final atomic model of the whole film, itself a measurement (RESIRE with an extended object,
tracing, refinement), not a ground truth.

Each sub-area is written as a tilt-series directory (the stack ``Proj_sub[x, y, tilt]`` as
``(tilt, x, y)``, tilt axis y, tilt centre at pixel ``CropHalf[:2]``), with the authors' model
in the sub-area's centred frame as its truth file; scoring follows the data's README:

* the film is wider than the field of view and not flat, so only the model's atoms in the
  interior (10 px in from each x edge, 4 px from each y edge) and between the lowest and the
  highest model atom there, plus 1.5 Å, are counted;
* after the Miao group's iterated global shift, a model atom is found when a reconstructed one
  lies within 0.75 Å (one-to-one); reconstructed atoms in the scored region matched to no model
  atom (anywhere) are extra; RMSD over the found atoms.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gaussian_atoms_method.atoms.atom_set import AtomSet
from gaussian_atoms_method.atoms.matching import global_shift, match_atoms
from gaussian_atoms_method.atoms.pair_distribution import nearest_neighbour_distances
from gaussian_atoms_method.physics.microscope import ProbeOptics

PIXEL_SIZE_A = 0.3216
"""The authors' pixel size, Å (README)."""
FULL_VOLUME_CENTRE_VOX = np.array([201.0, 176.0, 171.0])
"""The model's origin in the authors' 401 x 351 x 341 volume, 1-based voxels (README)."""
AREAS = (8, 21, 23, 25)
INTERIOR_PX = (10, 4)
"""Scored interior: this many pixels in from each x and each y edge (README)."""
DEPTH_MARGIN_A = 1.5
MATCH_RADIUS_A = 0.75
CLOSE_PAIR_A = 1.9
"""The data README's check of a physical report: 1.6% of the model's atoms have a neighbour closer
than this (Ta-Ta bonds 2.5-3.0 Å)."""
CITATION = "Yuan et al., Nature Materials 21, 95-102 (2022)"
FILM_FLAGS = ("--pipeline.model.extended-object", "on")
"""The specimen is a film, and the benchmark says so, as a user who knows it would: the reading
from the views alone (``physics/field_of_view.film_evidence``) is weak where the views' gains
scatter (a replica of a sub-area read it under its level and lost the atoms at one edge)."""


def _mat(path: Path, name: str) -> np.ndarray:
    from gaussian_atoms_method.film.subareas import mat_variable

    if not path.is_file():
        raise FileNotFoundError(f"{path}: not found (the Ta film data, ../shared/data/ta_film)")
    return mat_variable(path, name)


def area_geometry(data_dir: Path, area: int) -> tuple[np.ndarray, np.ndarray]:
    """The sub-area's ``CropCen`` and ``CropHalf`` (1-based voxels of the full volume)."""
    align = Path(data_dir) / "alignPara.mat"
    return _mat(align, "CropCen")[area - 1], _mat(align, "CropHalf")[area - 1]


def model_in_area_A(data_dir: Path, area: int) -> np.ndarray:
    """(M, 3) the authors' whole-film model in the sub-area's frame, Å about its tilt centre
    (README's geometry: ``local = model / px + centre - (CropCen - CropHalf)``, 0-based voxels
    of the sub-volume: the model is ``(1-based full-volume voxel - centre) * px``, and a
    sub-volume's 0-based index ``i`` is the full volume's 1-based ``CropCen - CropHalf + i``)."""
    cen, half = area_geometry(data_dir, area)
    model = _mat(Path(data_dir) / "Final_atomic_model_Ta_film.mat", "model").T
    local = model / PIXEL_SIZE_A + FULL_VOLUME_CENTRE_VOX - (cen - half)
    return (local - half) * PIXEL_SIZE_A


def prepare_area(data_dir: Path, out_dir: Path, area: int, species: str = "") -> Path:
    """Write one sub-area as a tilt-series directory, the model as its truth file, and
    ``species`` (e.g. "Ta"; "" for none) in its manifest."""
    from dataparsers.tilt_series_format import write_tilt_series

    data_dir = Path(data_dir)
    stack = _mat(data_dir / f"Projections_area{area}.mat", "Proj_sub")  # (x, y, tilt)
    angles = _mat(data_dir / "angles.mat", "angle")  # (phi, theta, psi): phi and psi within 0.4 degrees (README)
    _, half = area_geometry(data_dir, area)
    model = model_in_area_A(data_dir, area)
    return write_tilt_series(
        Path(out_dir) / f"area{area}",
        np.moveaxis(stack, 2, 0).astype(np.float32),
        angles,
        PIXEL_SIZE_A,
        truth=AtomSet(positions=model, species=np.array(["Ta"] * len(model))),
        centre_px=(float(half[0]), float(half[1])),
        extra={"description": f"Ta film sub-area {area}, ADF-STEM, {CITATION}"},
        species=species or (),
        euler_convention="zyx",  # RESIRE's Z-Y-X
    )


def write_model_start(data_dir: Path, area_dir: Path, area: int) -> Path:
    """Write the authors' model as a start (``--pipeline.model.start-atoms``): the model's atoms
    that reach the detector at some tilt, moved onto the data's frame by the global shift
    that takes our back-projection candidates onto the model (a small residual shift, README).
    A fit started there keeps what the data hold of the model and moves off the rest."""
    from dataparsers.tilt_series_format import load_tilt_series
    from gaussian_atoms_method.atoms.atom_set import write_atoms
    from gaussian_atoms_method.atoms.candidates import backprojection_candidates

    series = load_tilt_series(area_dir)
    model = model_in_area_A(data_dir, area)
    height_A, width_A = (np.array(series.projections.shape[1:]) - 1) * PIXEL_SIZE_A
    cx, cy = np.asarray(series.centre_px) * PIXEL_SIZE_A
    theta = np.deg2rad(series.angles_deg)[:, None]
    across = model[None, :, 0] * np.cos(theta) - model[None, :, 2] * np.sin(theta)  # (tilts, atoms), tilt axis y
    seen = (
        np.any((across >= -cx) & (across <= height_A - cx), axis=0)
        & (model[:, 1] >= -cy)
        & (model[:, 1] <= width_A - cy)
    )
    candidates = backprojection_candidates(
        series.projections, series.angles_deg, series.pixel_size_A, series.tilt_axis, series.centre_px, None
    )
    shift = global_shift(candidates, model[seen], MATCH_RADIUS_A)
    return write_atoms(
        AtomSet(positions=model[seen] - shift, species=np.array(["Ta"] * int(seen.sum()))),
        Path(area_dir) / "model_start.xyz",
    )


def scored_region(
    model_A: np.ndarray, shape_px: tuple[int, int], centre_px: tuple[float, float]
) -> tuple[np.ndarray, np.ndarray]:
    """(2, 3) lower and upper corners (Å) of the scored region: the detector's interior
    (:data:`INTERIOR_PX`) and the depth of the model's atoms inside it plus
    :data:`DEPTH_MARGIN_A`; and the (M,) mask of the model's atoms inside.  Where no model atom
    lies inside the interior (strip 1's sub-area 16, past the film's edge) the region is empty:
    nothing is scored there.

    >>> box, inside = scored_region(np.array([[100.0, 0.0, 0.0]]), (131, 61), (65.0, 30.0))
    >>> bool(inside.any()), bool((box[0] > box[1]).any())
    (False, True)
    """
    h, w = shape_px
    lo_xy = (np.array(INTERIOR_PX, dtype=np.float64) - np.asarray(centre_px)) * PIXEL_SIZE_A
    hi_xy = (
        np.array([h - 1 - INTERIOR_PX[0], w - 1 - INTERIOR_PX[1]], dtype=np.float64) - np.asarray(centre_px)
    ) * PIXEL_SIZE_A
    xy = np.all((model_A[:, :2] >= lo_xy) & (model_A[:, :2] <= hi_xy), axis=1)
    z = model_A[xy, 2]
    lo = np.r_[lo_xy, z.min() - DEPTH_MARGIN_A if len(z) else np.inf]
    hi = np.r_[hi_xy, z.max() + DEPTH_MARGIN_A if len(z) else -np.inf]
    return np.stack([lo, hi]), np.all((model_A >= lo) & (model_A <= hi), axis=1)


def score_area(
    pred_A: np.ndarray, model_A: np.ndarray, shape_px: tuple[int, int], centre_px: tuple[float, float]
) -> dict:
    """Found fraction, extra atoms per model atom and RMSD in the scored region (module text)."""
    box, inside = scored_region(model_A, shape_px, centre_px)
    return score_in_region(pred_A, model_A, box, inside)


def matched_to_model(pred_A: np.ndarray, model_A: np.ndarray, inside: np.ndarray):
    """Atoms ``pred_A`` (M, 3) moved by the global shift onto the model's atoms ``inside`` the
    scored region, and matched one-to-one to the model within :data:`MATCH_RADIUS_A`: the
    shifted (M, 3) positions, the (3,) shift (Å) and the matched pairs' indices into them and
    into ``model_A``."""
    pred = np.asarray(pred_A, dtype=np.float64).reshape(-1, 3)
    shift = global_shift(pred, model_A[inside], MATCH_RADIUS_A) if len(pred) and inside.any() else np.zeros(3)
    pred = pred + shift
    pred_i, model_i = match_atoms(pred, model_A, MATCH_RADIUS_A)
    return pred, shift, pred_i, model_i


def misses_and_extras(pred_A: np.ndarray, model_A: np.ndarray, box: np.ndarray, inside: np.ndarray):
    """:func:`matched_to_model`, sorted for a study of what went wrong: the shifted (M, 3)
    positions, the (3,) shift, the (M,) mask of those matched, the (M,) mask of those in the
    region ``box``, and the indices of the model atoms ``inside`` that none matches and of the
    atoms in the region that match none."""
    pred, shift, pred_i, model_i = matched_to_model(pred_A, model_A, inside)
    matched = np.zeros(len(pred), dtype=bool)
    matched[pred_i] = True
    found = np.zeros(len(model_A), dtype=bool)
    found[model_i] = True
    in_box = np.all((pred >= box[0]) & (pred <= box[1]), axis=1)
    return pred, shift, matched, in_box, np.flatnonzero(inside & ~found), np.flatnonzero(in_box & ~matched)


def missed_nearby(pred_A: np.ndarray, model_A: np.ndarray, missed: np.ndarray, extra: np.ndarray, near_A: float):
    """For each atom ``extra`` (indices into the shifted ``pred_A`` of :func:`misses_and_extras`):
    how many of the ``missed`` model atoms (indices into ``model_A``) lie within ``near_A``, and
    the one (its index into ``model_A``) where exactly one does, else -1: an extra atom beside
    exactly one miss is that atom placed elsewhere."""
    count, partner = np.zeros(len(extra), dtype=np.int64), np.full(len(extra), -1, dtype=np.int64)
    if len(missed) and len(extra):
        from scipy.spatial import cKDTree

        near = cKDTree(model_A[missed]).query_ball_point(pred_A[extra], near_A)
        count = np.array([len(n) for n in near], dtype=np.int64)
        partner = np.array([missed[n[0]] if len(n) == 1 else -1 for n in near], dtype=np.int64)
    return count, partner


def most_reportable(model_A: np.ndarray, inside: np.ndarray, hard_core_A: float) -> int:
    """How many of the model's atoms ``inside`` the scored region a report that obeys the hard core
    could hold where the model puts them: the most of them with no two closer than
    ``hard_core_A`` (the largest independent set of each group of atoms joined by such pairs).
    The authors' model is a measurement and holds pairs no material has (down to 1.53 Å against
    tantalum's 1.87): scored against it, a physical report drops one of each such pair, or finds
    both only by holding them apart (each within the match radius of its place).  A replica's
    truth keeps fewer still: none closer than the shortest bond (:func:`write_replica`).

    >>> model = np.array([[0.0, 0, 0], [1.5, 0, 0], [3.0, 0, 0], [10.0, 0, 0]])
    >>> most_reportable(model, np.ones(4, bool), 1.87)  # a chain of three keeps its two ends
    3
    """
    from gaussian_atoms_method.atoms.hard_core import most_apart

    return int(most_apart(np.asarray(model_A, dtype=np.float64)[np.asarray(inside, bool)], hard_core_A).sum())


def score_in_region(pred_A: np.ndarray, model_A: np.ndarray, box: np.ndarray, inside: np.ndarray) -> dict:
    """The scores of atoms ``pred_A`` against the model's atoms ``inside`` the region ``box``
    ((2, 3) lower and upper corners, Å), after the global shift: found (within
    :data:`MATCH_RADIUS_A`, one-to-one), extra per model atom (atoms in the box matched to no
    model atom anywhere), RMSD over the found, and the share of atoms in the box with a
    neighbour under :data:`CLOSE_PAIR_A`."""
    pred, shift, pi, ti = matched_to_model(pred_A, model_A, inside)
    found = inside[ti]
    pred_inside = np.all((pred >= box[0]) & (pred <= box[1]), axis=1)
    matched = np.zeros(len(pred), dtype=bool)
    matched[pi] = True
    n_model = int(inside.sum())
    err = pred[pi[found]] - model_A[ti[found]]
    close = (
        nearest_neighbour_distances(pred)[pred_inside] < CLOSE_PAIR_A
        if len(pred) >= 2
        else np.zeros(int(pred_inside.sum()), dtype=bool)
    )
    return {
        "n_model": n_model,
        "n_pred": int(pred_inside.sum()),
        "n_found": int(found.sum()),
        "found": float(found.sum()) / n_model if n_model else float("nan"),
        "extra_per_model_atom": float((pred_inside & ~matched).sum()) / n_model if n_model else float("nan"),
        "rmsd_pm": float(np.sqrt((err**2).sum(axis=1).mean()) * 100.0) if len(err) else float("nan"),
        "share_close": float(close.mean()) if len(close) else 0.0,
        "shift_A": shift.tolist(),
    }


def evidence_in_region(
    atoms: AtomSet, model_A: np.ndarray, box: np.ndarray, inside: np.ndarray, shift_A: np.ndarray
) -> dict:
    """:func:`gaussian_atoms_method.atoms.evidence.evidence_scores` of the reported ``atoms`` in the
    region ``box`` against the model's atoms ``inside`` it, after the global shift ``shift_A``
    (:func:`score_in_region`'s; empty without the atoms' evidence).  As there, every atom is
    matched to the whole model: an atom in the region whose model atom lies just outside it is
    not false (on a replica of sub-area 8, two of five such were)."""
    from gaussian_atoms_method.atoms.evidence import evidence_scores

    if atoms.proven is None or not len(atoms):
        return {}
    shift = np.asarray(shift_A, dtype=np.float64)
    pred = atoms.positions + shift
    in_box = np.all((pred >= box[0]) & (pred <= box[1]), axis=1)
    # every atom matched as score_in_region matches them, those in the region scored
    return evidence_scores(atoms.shifted(shift), AtomSet(model_A), MATCH_RADIUS_A, False, in_box, inside)


REPLICA = {
    "support_A": 30.0,
    "probe": "aberrated",
    "optics": ProbeOptics(source_fwhm_A=0.7, halo_fraction=0.06),
    "shift_px": 0.5,
    "gain_scatter": 0.068,
}
"""The Ta experiment's replica, through physics the fit does not share (abTEM's Lobato potentials
with ADF contrast, :func:`~gaussian_atoms_method.harness.replica.replica_of`'s default): an
amorphous carbon support of a common 3 nm, a 300 kV probe with its rings and tails, a 0.7 Å
source and a 6% halo (issue 85's replica of the film), the views' misregistration (0.5 px RMS
across the tilt axis, measured against any atom set) and their gains' scatter (6.8%, measured),
as issue 67 read them off the film."""


def within_core_words(scores: dict, species: str) -> str:
    """The model's own atoms a physical report cannot hold where the model puts them
    (:func:`most_reportable`), where there are any."""
    n = scores.get("model_atoms_within_core", 0)
    if not n:
        return ""
    return (
        f"; {n} of the model's atoms lie within {species}'s hard core of another: a physical report misses "
        f"them or holds those pairs apart"
    )


def evidence_words(scores: dict) -> str:
    """The evidence part of a sub-area's line ("" without it)."""
    if "proven" not in scores:
        return ""
    share, found = scores.get("open_share_of_disagreement"), scores.get("proven_found")
    cover = scores.get("trusted_share_of_truth")
    return (
        f"; {scores['proven']} proven, {scores['open']} open, {scores['depth_open']} open in depth"
        + (f" (the rest {found:.3f} on a model atom)" if found is not None else "")
        + (f", trusted atoms on {cover:.3f} of the model's" if cover is not None else "")
        + (f", the open ones hold {share:.0%} of the disagreement" if share is not None else "")
        + (
            "; 95% intervals hold x/y/z "
            + "/".join(f"{c:.2f}" for c in scores["coverage_95_xyz"])
            + (
                ", missing an error of " + "/".join(f"{f * 100:.1f}" for f in scores["precision_floor_A"]) + " pm"
                if "precision_floor_A" in scores
                else ""
            )
            if "coverage_95_xyz" in scores
            else ""
        )
    )


def write_replica(area_dir: Path, out_dir: Path, seed: int = 0) -> Path:
    """A replica of the sub-area ``area_dir`` (:data:`REPLICA`'s experiment;
    :func:`gaussian_atoms_method.harness.replica.write_replica`) as a tilt-series directory
    ``out_dir``; its atoms and truth are the model's atoms a specimen can hold
    (:func:`~gaussian_atoms_method.harness.replica.physical_truth`: one of each pair closer than
    the shortest bond tantalum can form set aside)."""
    from dataparsers.tilt_series_format import load_tilt_series
    from gaussian_atoms_method.atoms.atom_set import read_atoms
    from gaussian_atoms_method.harness import replica

    if (out_dir / "tilt_series.json").is_file():
        return out_dir
    series = load_tilt_series(area_dir)
    description = {"description": f"a replica of {area_dir} ({REPLICA}, seed {seed}); the model, {CITATION}"}
    truth, _, _ = replica.physical_truth(read_atoms(series.truth_path))
    return replica.write_replica(series, truth, out_dir, extra=description, seed=seed, **REPLICA)[0]


@dataclass
class FilmBenchmark:
    """Reconstruct each sub-area with ``ns-train gaussian-atoms`` (the defaults, the specimen
    said to be a film: :data:`FILM_FLAGS`) and score it."""

    data_dir: Path
    output: Path
    areas: tuple[int, ...] = AREAS
    iterations: int = 3000
    device: str = "cpu"
    flags: tuple[str, ...] = ()
    species: str = "Ta"
    start_from_model: bool = False
    replica: bool = False
    """Fit each sub-area's replica instead (:func:`write_replica`): the model, less its pairs closer
    than the shortest bond tantalum can form, as a known truth in the sub-area's own geometry,
    level and noise, alone (:func:`.film_replica.replica_film` fits it with its strip neighbours'
    as a film)."""

    def score(self, area: int, data: Path, atoms) -> dict:
        """The sub-area's atoms scored in its interior against :meth:`truth_A`, with their evidence."""
        from dataparsers.tilt_series_format import load_tilt_series
        from gaussian_atoms_method.atoms.hard_core import hard_core_from_species

        series = load_tilt_series(data)
        model = self.truth_A(area, series)
        box, inside = scored_region(model, series.projections.shape[1:], tuple(series.centre_px))
        scores = score_in_region(atoms.positions, model, box, inside)
        if self.species:
            core = hard_core_from_species(self.species)
            scores["model_atoms_within_core"] = int(scores["n_model"]) - most_reportable(model, inside, core)
        evidence = evidence_in_region(atoms, model, box, inside, scores["shift_A"])
        return scores | evidence | {"n_atoms_reported": len(atoms)}

    def run(self) -> list[dict]:
        from gaussian_atoms_method.harness.benchmark import scored_run

        rows = []
        for area in self.areas:
            run_dir = self.output / "runs" / f"area{area}"
            flags = self.film_flags() + (
                ("--pipeline.model.start-atoms", str(self.output / "data" / f"area{area}" / "model_start.xyz"))
                if self.start_from_model
                else ()
            )
            s = scored_run(
                run_dir / "film_scores.json",
                run_dir,
                lambda area=area: self.prepare(area),
                lambda data, atoms, area=area: self.score(area, data, atoms),
                self.iterations,
                self.device,
                flags,
            )
            rows.append({"area": area, **s})
            self.say(rows[-1])
        self.write(rows)
        self.overlaps()
        return rows

    def say(self, s: dict, how: str = "") -> None:
        if not s["n_model"]:  # past the film's edge (strip 1's sub-area 16): nothing to score against
            print(
                f"Ta film area {s['area']}{how}: no atom of the {'truth' if self.replica else 'model'} in its "
                f"interior, nothing scored ({s.get('n_atoms_reported', s['n_pred'])} atoms reported), "
                f"{s['seconds']:.0f} s",
                flush=True,
            )
            return
        print(
            f"Ta film area {s['area']}{how}: found {s['found']:.3f} of {s['n_model']} model atoms, extra "
            f"{s['extra_per_model_atom']:.3f} per model atom, RMSD {s['rmsd_pm']:.1f} pm, {s['share_close']:.1%} "
            f"of atoms closer than {CLOSE_PAIR_A} Å to another, {s['seconds']:.0f} s"
            + evidence_words(s)
            + within_core_words(s, self.species),
            flush=True,
        )

    def overlaps(self) -> list:
        """The fitted sub-areas that overlap, judged on each other without a truth
        (:func:`~gaussian_atoms_method.film.stitch.pair_agreement`, their atoms moved into the
        film's frame by their crops' centres): printed and written to ``overlaps.csv``."""
        from gaussian_atoms_method.atoms.atom_set import read_atoms
        from gaussian_atoms_method.atoms.hard_core import hard_core_from_species
        from gaussian_atoms_method.film.stitch import Reports, pair_agreement, write_overlaps
        from gaussian_atoms_method.film.subareas import published_subareas

        # the sub-areas' frames in the film's, as `film` places them (their directories are written)
        subareas = published_subareas(
            self.data_dir, list(self.areas), self.output / "data", PIXEL_SIZE_A, FULL_VOLUME_CENTRE_VOX
        )
        reports, trusted = [], []
        for sub in subareas:
            atoms = read_atoms(self.output / "runs" / sub.name / "ours" / "gaussian-atoms" / "run" / "atoms.xyz")
            reports.append(
                Reports(sub.name, atoms.positions + np.asarray(sub.offset_A), sub.interior_A, atoms.position_std_A)
            )
            trusted.append(np.ones(len(atoms), bool) if atoms.trusted is None else atoms.trusted.astype(bool))
        core = hard_core_from_species(self.species or "Ta")
        pairs = pair_agreement(reports, core)
        write_overlaps(pairs, self.output / "overlaps.csv")
        for p, t in zip(pairs, pair_agreement(reports, core, trusted)):
            print(
                f"Ta film {p.a} and {p.b} (common interior {p.common_A2:.0f} Å²): {p.agree_a:.3f} of {p.n_a} atoms of "
                f"{p.a} there reported by {p.b}, {p.agree_b:.3f} of its {p.n_b} by {p.a}; of the trusted ones "
                f"{t.agree_a:.3f} of {t.n_a} and {t.agree_b:.3f} of {t.n_b}" + p.position_words(),
                flush=True,
            )
        return pairs

    def truth_A(self, area: int, series) -> np.ndarray:
        """What the sub-area's atoms are scored against: the authors' model on the real views, the
        replica's own truth on a replica ``series`` (the model less its pairs closer than the shortest
        bond tantalum can form)."""
        if not self.replica:
            return model_in_area_A(self.data_dir, area)
        from gaussian_atoms_method.atoms.atom_set import read_atoms

        return read_atoms(series.truth_path).positions - np.asarray(series.origin_A)

    def film_flags(self) -> tuple[str, ...]:
        """The run's options: :data:`FILM_FLAGS`, then the user's ``flags`` (an option given twice
        takes its last value, so the user's extended-object option replaces the film's)."""
        return FILM_FLAGS + self.flags

    def prepare(self, area: int) -> Path:
        """The sub-area's tilt-series directory (and the model as its start, if asked)."""
        area_dir = prepare_area(self.data_dir, self.output / "data", area, self.species)
        if self.replica:
            area_dir = write_replica(area_dir, self.output / "data" / "replica" / f"area{area}", seed=area)
        if self.start_from_model:
            write_model_start(self.data_dir, area_dir, area)
        return area_dir

    def write(self, rows: list[dict]) -> None:
        self.output.mkdir(parents=True, exist_ok=True)
        fields = (
            "area n_model n_pred n_found found extra_per_model_atom rmsd_pm share_close model_atoms_within_core "
            "seconds proven open depth_open proven_found trusted_share_of_truth open_share_of_disagreement "
            "coverage_95_xyz depth_coverage_95 precision_floor_A registered"
        ).split()
        with open(self.output / "results.csv", "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
            writer.writeheader()
            writer.writerows(rows)
        lines = [
            f"Data: {CITATION}.",
            "",
            f"| sub-area | model atoms scored | found (≤ 0.75 Å) | extra per model atom | RMSD (pm) | atoms < "
            f"{CLOSE_PAIR_A} Å apart | time (s) |",
            "| --- | --- | --- | --- | --- | --- | --- |",
        ]
        lines += [
            f"| {r['area']} | {r['n_model']} | {r['found']:.3f} | {r['extra_per_model_atom']:.3f} | {r['rmsd_pm']:.1f} "
            f"| {r.get('share_close', float('nan')):.1%} | {r['seconds']:.0f} |"
            for r in rows
        ]
        (self.output / "results.md").write_text("\n".join(lines) + "\n")
