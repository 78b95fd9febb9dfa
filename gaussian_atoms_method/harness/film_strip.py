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

from gaussian_atoms_method.atoms.matching import match_atoms
from gaussian_atoms_method.harness.film_benchmark import (
    CITATION,
    DEPTH_MARGIN_A,
    FULL_VOLUME_CENTRE_VOX,
    MATCH_RADIUS_A,
    PIXEL_SIZE_A,
    _mat,
    score_in_region,
)

STRIPS = {1: tuple(range(1, 17)), 2: tuple(range(17, 30))}
"""The published strips: rows of ``alignPara.mat`` (the data's README)."""


def score_strip(film_dir: Path, data_dir: Path) -> dict:
    """Found, extra per model atom, RMSD, close pairs, the overlap's reproducibility and (where the
    film says) its trusted atoms: how many, the share on a model atom and of the model's atoms, of the
    film in ``film_dir`` (its ``atoms.csv`` and ``film.json``) against the authors' model."""
    from gaussian_atoms_method.film.subareas import read_plan

    subareas = read_plan(Path(film_dir) / "film.json")
    table = np.loadtxt(Path(film_dir) / "atoms.csv", delimiter=",", skiprows=1, ndmin=2)
    positions, found_in, covered_by, reported = table[:, :3], table[:, 3], table[:, 4], table[:, 6] > 0
    pred = positions[reported]
    model = _mat(Path(data_dir) / "Final_atomic_model_Ta_film.mat", "model").T
    corners = np.array([s.interior_A for s in subareas])  # (S, 2, 2)
    lo_xy, hi_xy = corners[:, 0].min(axis=0), corners[:, 1].max(axis=0)
    lo_xy[1], hi_xy[1] = corners[:, 0, 1].max(), corners[:, 1, 1].min()  # along the axis: the common extent
    in_xy = np.all((model[:, :2] >= lo_xy) & (model[:, :2] <= hi_xy), axis=1)
    z = model[in_xy, 2]
    lo, hi = np.r_[lo_xy, z.min() - DEPTH_MARGIN_A], np.r_[hi_xy, z.max() + DEPTH_MARGIN_A]
    inside = np.all((model >= lo) & (model <= hi), axis=1)
    scores = score_in_region(pred, model, np.stack([lo, hi]), inside)
    if table.shape[1] > 11 and np.all(np.isfinite(table[:, 11])):  # the film's trusted atoms
        trusted = score_in_region(positions[table[:, 11] > 0], model, np.stack([lo, hi]), inside)
        scores["trusted"] = trusted["n_pred"]
        unmatched = trusted["extra_per_model_atom"] * trusted["n_model"]
        scores["trusted_on_model"] = 1.0 - unmatched / max(trusted["n_pred"], 1)
        scores["trusted_share_of_model"] = trusted["found"]
    share = found_in[reported] / np.maximum(covered_by[reported], 1)
    return scores | {
        "median_found_in": float(np.median(found_in[reported])),
        "median_covered_by": float(np.median(covered_by[reported])),
        "median_share_found": float(np.median(share)),
        "citation": CITATION,
    }


def run_strip(
    strip: int,
    data_dir: Path,
    output: Path,
    device: str = "cpu",
    address: str | None = None,
    tasks_per_gpu: int = 1,
    registration_by_overlap: bool = True,
    species: str | None = "Ta",
    max_steps: int = 3000,
) -> dict:
    """Fit and join a published strip of the Ta film (resumable) and score it; with
    ``registration_by_overlap`` its per-view shifts and gains decided by its overlapping sub-areas
    (:mod:`gaussian_atoms_method.film.registration`); ``species`` and ``max_steps`` as
    :func:`~gaussian_atoms_method.film.film.reconstruct_film` takes them."""
    from gaussian_atoms_method.film.film import reconstruct_film
    from gaussian_atoms_method.film.subareas import published_subareas

    output = Path(output) / f"strip{strip}"
    subareas = published_subareas(
        data_dir, list(STRIPS[strip]), output / "data", PIXEL_SIZE_A, tuple(FULL_VOLUME_CENTRE_VOX)
    )
    reconstruct_film(
        subareas,
        output,
        device,
        species,
        max_steps,
        address=address,
        tasks_per_gpu=tasks_per_gpu,
        registration_by_overlap=registration_by_overlap,
    )
    scores = score_strip(output, data_dir)
    (output / "scores.json").write_text(json.dumps(scores, indent=1) + "\n")
    return scores


def simulated_film(
    output: Path,
    scale: float = 0.5,
    noise_std: float = 50.0,
    device: str = "cpu",
    address: str | None = None,
    registration_by_overlap: bool = True,
) -> dict:
    """The harness's film (amorphous Pd, 110 x 50 x 20 Å times ``scale`` across, Lobato potentials,
    limited tilts), measured as one series over its whole width, cut into tiles 40 Å across
    every 15 Å (along the axis: the whole field), fitted on Ray and joined; scored against the
    truth in the tiles' interiors: found, false per true atom, RMSD, and the atoms lost or
    doubled (pairs under the hard core) within 3 Å of a tile's interior edge, the seams."""
    from scipy.spatial import cKDTree

    from dataparsers.tilt_series_format import TiltSeries
    from gaussian_atoms_method.atoms.hard_core import hard_core_from_species
    from gaussian_atoms_method.atoms.matching import score_atoms
    from gaussian_atoms_method.film.film import reconstruct_film
    from gaussian_atoms_method.film.stitch import Reports
    from gaussian_atoms_method.film.subareas import tile_series
    from gaussian_atoms_method.harness.particles import make_particle
    from gaussian_atoms_method.harness.simulate import parse_tilts, simulate_tilt_series

    output = Path(output)
    truth = make_particle("film", scale=scale)
    sim = simulate_tilt_series(truth, parse_tilts("limited"), potential="lobato", noise_std=noise_std, seed=0)
    series = TiltSeries(sim.projections, sim.angles_deg, sim.pixel_size_A, "y")
    px = sim.pixel_size_A
    subareas = tile_series(
        series, (round(40 / px), series.projections.shape[2]), (round(15 / px), 10**6), output / "data"
    )
    film = reconstruct_film(
        subareas, output, device, "Pd", address=address, registration_by_overlap=registration_by_overlap
    )
    reported = film.positions[film.reported]
    true = sim.truth.positions
    union = np.zeros(len(true), dtype=bool)
    for s in subareas:
        union |= Reports(s.name, true, s.interior_A).inside(true)
    scores = score_atoms(reported, true[union])
    edges = np.concatenate([s.interior_A[:, 0] for s in subareas])
    seam = np.min(np.abs(true[union][:, :1] - edges[None, :]), axis=1) < 3.0
    _, ti = match_atoms(reported, true[union], MATCH_RADIUS_A)
    lost = np.ones(int(union.sum()), dtype=bool)
    lost[ti] = False
    doubled = len(cKDTree(reported).query_pairs(hard_core_from_species("Pd")))
    result = scores | {
        "sub_areas": len(subareas),
        "lost_at_seams": int((lost & seam).sum()),
        "true_at_seams": int(seam.sum()),
        "pairs_under_hard_core": doubled,
    }
    (output / "scores.json").write_text(json.dumps(result, indent=1) + "\n")
    return result
