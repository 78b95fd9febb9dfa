"""The Ta film's strips stitched: the published sub-areas of one strip fitted on Ray
(:func:`gaussian_atoms_method.film.film.reconstruct_film`) and the joined atoms scored against the
authors' model in the strip's interior.

Data and citation: :mod:`.film_benchmark`.  The scored region is the union of the sub-areas'
interiors (a strip's sub-areas share their extent along the tilt axis, so the union is a
rectangle) and the depth of the model's atoms there plus 1.5 Å; after the global shift, a model
atom is found when a joined atom lies within 0.75 Å (one-to-one), as for one sub-area.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from gaussian_atoms_method.atoms.matching import global_shift, match_atoms
from gaussian_atoms_method.atoms.pair_distribution import nearest_neighbour_distances
from gaussian_atoms_method.harness.film_benchmark import (
    CITATION,
    CLOSE_PAIR_A,
    DEPTH_MARGIN_A,
    FULL_VOLUME_CENTRE_VOX,
    MATCH_RADIUS_A,
    PIXEL_SIZE_A,
    _mat,
)

STRIPS = {1: tuple(range(1, 17)), 2: tuple(range(17, 30))}
"""The published strips: rows of ``alignPara.mat`` (the data's README)."""


def score_strip(film_dir: Path, data_dir: Path) -> dict:
    """Found, extra per model atom, RMSD, close pairs and the overlap's reproducibility of the
    film in ``film_dir`` (its ``atoms.csv`` and ``film.json``) against the authors' model."""
    from gaussian_atoms_method.film.subareas import read_plan

    subareas = read_plan(Path(film_dir) / "film.json")
    table = np.loadtxt(Path(film_dir) / "atoms.csv", delimiter=",", skiprows=1, ndmin=2)
    positions, found_in, covered_by, confirmed = table[:, :3], table[:, 3], table[:, 4], table[:, 5] > 0
    pred = positions[confirmed]
    model = _mat(Path(data_dir) / "Final_atomic_model_Ta_film.mat", "model").T
    corners = np.array([s.interior_A for s in subareas])  # (S, 2, 2)
    lo_xy, hi_xy = corners[:, 0].min(axis=0), corners[:, 1].max(axis=0)
    lo_xy[1], hi_xy[1] = corners[:, 0, 1].max(), corners[:, 1, 1].min()  # along the axis: the common extent
    in_xy = np.all((model[:, :2] >= lo_xy) & (model[:, :2] <= hi_xy), axis=1)
    z = model[in_xy, 2]
    lo, hi = np.r_[lo_xy, z.min() - DEPTH_MARGIN_A], np.r_[hi_xy, z.max() + DEPTH_MARGIN_A]
    inside = np.all((model >= lo) & (model <= hi), axis=1)
    shift = global_shift(pred, model[inside], MATCH_RADIUS_A)
    pred = pred + shift
    pi, ti = match_atoms(pred, model, MATCH_RADIUS_A)
    found = inside[ti]
    pred_inside = np.all((pred >= lo) & (pred <= hi), axis=1)
    matched = np.zeros(len(pred), dtype=bool)
    matched[pi] = True
    err = pred[pi[found]] - model[ti[found]]
    close = nearest_neighbour_distances(pred)[pred_inside] < CLOSE_PAIR_A
    n = int(inside.sum())
    share = found_in[confirmed] / np.maximum(covered_by[confirmed], 1)
    return {
        "n_model": n,
        "n_pred": int(pred_inside.sum()),
        "found": float(found.sum()) / n,
        "extra_per_model_atom": float((pred_inside & ~matched).sum()) / n,
        "rmsd_pm": float(np.sqrt((err**2).sum(axis=1).mean()) * 100.0),
        "share_close": float(close.mean()) if len(close) else 0.0,
        "median_found_in": float(np.median(found_in[confirmed])),
        "median_covered_by": float(np.median(covered_by[confirmed])),
        "median_share_found": float(np.median(share)),
        "shift_A": shift.tolist(),
        "citation": CITATION,
    }


def run_strip(strip: int, data_dir: Path, output: Path, device: str = "cpu", address: str | None = None) -> dict:
    """Fit and join a published strip of the Ta film (resumable) and score it."""
    from gaussian_atoms_method.film.film import reconstruct_film
    from gaussian_atoms_method.film.subareas import published_subareas

    output = Path(output) / f"strip{strip}"
    subareas = published_subareas(
        data_dir, list(STRIPS[strip]), output / "data", PIXEL_SIZE_A, tuple(FULL_VOLUME_CENTRE_VOX)
    )
    reconstruct_film(subareas, output, device, "Ta", address=address)
    scores = score_strip(output, data_dir)
    (output / "scores.json").write_text(json.dumps(scores, indent=1) + "\n")
    return scores
