"""Which of a Ta-film sub-area's atoms disagree with the authors' model, and does any reading of
the fit tell them apart?

Fits one sub-area (the real views, or with ``--replica-seed`` a replica of them) with several
seeds through ``ga.reconstruct`` and prints, in ``benchmark-film``'s region:

* each fit's scores (found / extra per model atom / RMSD) and evidence (the atoms not called
  open on a model atom; the open share of the disagreement; open in depth);
* the atoms not called open that lie on no model atom against those on one: their mass (in the
  matched atoms' median), significance and depth half-width, and how far the nearest model atom
  is (0.75-1.5 Å: the same atom placed elsewhere; how much along the beam);
* the evidence again with the atoms the other seeds' fits do not reproduce (none of theirs
  within the match radius) called open: whether agreement between fits of the same views sorts
  them.

    python scripts/studies/real_evidence.py --area 23 --device cuda
    python scripts/studies/real_evidence.py --area 8 --replica-seed 108 --device cuda
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--area", type=int, required=True, help="a sub-area of the film (8, 21, 23, 25, ...)")
    parser.add_argument("--film", type=Path, default=Path("../shared/data/ta_film"), help="the film's folder")
    parser.add_argument("--replica-seed", type=int, default=None, help="fit a replica of the sub-area instead")
    parser.add_argument("--seeds", type=int, nargs="+", default=[42, 1, 2])
    parser.add_argument("--device", default="auto")
    args = parser.parse_args()
    try:
        report(args)
    except (OSError, ValueError) as err:  # a missing film folder or file
        raise SystemExit(f"real_evidence.py: {err}") from None


def fits(args, work: Path) -> tuple[list, np.ndarray, np.ndarray, np.ndarray]:
    """Each seed's reported atoms and the model, the region and the model atoms inside it."""
    import json

    import gaussian_atoms_method as ga
    from gaussian_atoms_method.harness import film_benchmark as fb

    area_dir = fb.prepare_area(args.film, work, args.area, "Ta")
    if args.replica_seed is not None:
        area_dir = fb.write_replica(area_dir, work / "replica", seed=args.replica_seed)
    meta = json.loads((area_dir / "tilt_series.json").read_text())
    shape = np.load(area_dir / meta["projections"], mmap_mode="r").shape[1:]
    model = fb.model_in_area_A(args.film, args.area)
    box, inside = fb.scored_region(model, shape, tuple(meta["centre_px"]))
    series = ga.read_tilt_series(area_dir)
    runs = [ga.reconstruct(series, species="Ta", device=args.device, progress=False, seed=s) for s in args.seeds]
    return runs, model, box, inside


def report(args) -> None:
    """Print the study's tables for the parsed command line."""
    from scipy.spatial import cKDTree

    from gaussian_atoms_method.harness import film_benchmark as fb

    with tempfile.TemporaryDirectory() as work:
        runs, model, box, inside = fits(args, Path(work))
    shifted = []
    print("| seed | found / extra / RMSD pm | not open, on a model atom | open share | open in depth |")
    print("| --- | --- | --- | --- | --- |")
    for seed, atoms in zip(args.seeds, runs):
        s = fb.score_in_region(atoms.positions, model, box, inside)
        e = fb.evidence_in_region(atoms, model, box, inside, s["shift_A"])
        shifted.append(atoms.shifted(np.asarray(s["shift_A"])))
        print(
            f"| {seed} | {s['found']:.3f} / {s['extra_per_model_atom']:.3f} / {s['rmsd_pm']:.1f} | "
            f"{e['proven_found']:.2f} | {e['open_share_of_disagreement']:.2f} | {e['depth_open']} |"
        )
    print(
        "\n| seed | off the model: n, mass, significance, depth half-width Å | on it "
        "| nearest model 0.75-1.5 Å, |cos| to the beam |"
    )
    print("| --- | --- | --- | --- |")
    tree = cKDTree(model)
    for seed, atoms in zip(args.seeds, shifted):
        in_box = np.all((atoms.positions >= box[0]) & (atoms.positions <= box[1]), axis=1)
        closed = in_box & atoms.proven.astype(bool) & ~atoms.depth_open.astype(bool)
        distance, nearest = tree.query(atoms.positions)
        off, on = closed & (distance > fb.MATCH_RADIUS_A), closed & (distance <= fb.MATCH_RADIUS_A)
        mass = atoms.amplitudes * atoms.sigmas**3
        typical = np.median(mass[on])

        def medians(mask):
            return (
                f"{mask.sum()}, {np.median(mass[mask]) / typical:.2f}, {np.median(atoms.significance[mask]):.1f}, "
                f"{np.median(atoms.depth_halfwidth_A[mask]):.2f}"
            )

        near = off & (distance < 2 * fb.MATCH_RADIUS_A)
        along = model[nearest[near]] - atoms.positions[near]
        cos = np.mean(np.abs(along[:, 2]) / np.linalg.norm(along, axis=1)) if near.any() else float("nan")
        print(f"| {seed} | {medians(off)} | {medians(on)} | {near.sum()} of {off.sum()}, {cos:.2f} |")
    print("\n| seed | not reproduced by the other fits | not open, on a model atom | open share |")
    print("| --- | --- | --- | --- |")
    for i, atoms in enumerate(shifted):
        reproduced = np.ones(len(atoms), bool)
        for j, other in enumerate(shifted):
            if j != i:
                reproduced &= cKDTree(other.positions).query(atoms.positions)[0] <= fb.MATCH_RADIUS_A
        in_box = np.all((atoms.positions >= box[0]) & (atoms.positions <= box[1]), axis=1)
        marked = atoms.subset(np.ones(len(atoms), bool))
        marked.proven = (atoms.proven.astype(bool) & reproduced).astype(int)
        e = fb.evidence_in_region(marked, model, box, inside, np.zeros(3))
        print(
            f"| {args.seeds[i]} | {int((~reproduced & in_box).sum())} | {e['proven_found']:.2f} | "
            f"{e['open_share_of_disagreement']:.2f} |"
        )


if __name__ == "__main__":
    main()
