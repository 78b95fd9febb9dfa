"""What a Ta-film sub-area's misses and extra atoms are, against the authors' model.

Reads a finished ``gaussian-atoms benchmark-film`` sub-area (its data and run) and sorts, in the
scored region and after the benchmark's global shift:

* the model atoms we missed (none of ours within 0.75 Å, one-to-one): those with one of our
  unmatched atoms within ``--near-A`` (the same atom placed elsewhere: how far, and how much
  of that along the beam), and those with none;
* our extra atoms: beside one missed model atom, between two, or near none (with their mass
  against our matched atoms').

    python scripts/studies/film_misses.py --output outputs/benchmark-film --area 23
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--output", type=Path, required=True, help="a benchmark-film --output folder")
    parser.add_argument("--area", type=int, required=True)
    parser.add_argument("--film", type=Path, default=Path("../shared/data/ta_film"), help="the film's folder")
    parser.add_argument("--near-A", type=float, default=1.5, help="an extra atom this close to a missed one is it")
    args = parser.parse_args()
    try:
        report(args)
    except (OSError, ValueError) as err:  # a missing run or file, a series that cannot be read
        raise SystemExit(f"film_misses.py: {err}") from None


def report(args) -> None:
    """Print the study's tables for the parsed command line."""
    from scipy.spatial import cKDTree

    from gaussian_atoms_method.atoms.atom_set import read_atoms
    from gaussian_atoms_method.harness import film_benchmark as fb

    data = args.output / "data" / f"area{args.area}"
    meta = json.loads((data / "tilt_series.json").read_text())
    shape = np.load(data / meta["projections"], mmap_mode="r").shape[1:]
    model = fb.model_in_area_A(args.film, args.area)
    atoms = read_atoms(args.output / "runs" / f"area{args.area}" / "ours" / "gaussian-atoms" / "run" / "atoms.xyz")
    box, inside = fb.scored_region(model, shape, tuple(meta["centre_px"]))
    pred, _, matched, _, missed, extra = fb.misses_and_extras(atoms.positions, model, box, inside)
    found = inside.copy()
    found[missed] = False
    mass = atoms.amplitudes * (2 * np.pi * atoms.sigmas**2) ** 1.5
    typical = np.median(mass[matched])

    count, partner = fb.missed_nearby(pred, model, missed, extra, args.near_A)
    print(f"sub-area {args.area}: {int(inside.sum())} model atoms scored, {len(missed)} missed, {len(extra)} extra")
    distance, _ = cKDTree(pred[extra]).query(model[missed]) if len(extra) else (np.full(len(missed), np.inf), None)
    print(
        f"missed with an extra atom within {args.near_A} Å: {int((distance < args.near_A).sum())}; "
        f"with none: {int((distance >= args.near_A).sum())}"
    )
    print("| extra atoms | count | mass / our matched atoms' (median) | width Å (median) |")
    print("| --- | --- | --- | --- |")
    groups = (("beside one missed", count == 1), ("between two or more", count >= 2), ("near none", count == 0))
    for label, sel in groups:
        idx = extra[sel]
        if len(idx):
            width = np.median(atoms.sigmas[idx])
            print(f"| {label} | {len(idx)} | {np.median(mass[idx]) / typical:.2f} | {width:.2f} |")
    one = count == 1
    if one.any():
        offset = pred[extra[one]] - model[partner[one]]
        length = np.linalg.norm(offset, axis=1)
        print(
            f"beside one missed: offset {np.median(length):.2f} Å (median), {np.median(np.abs(offset[:, 2])):.2f} Å of "
            f"it along the beam; |cos| with the beam {np.median(np.abs(offset[:, 2]) / length):.2f}; mean sign of the "
            f"depth offset {np.mean(np.sign(offset[:, 2])):+.2f}"
        )
    nn = cKDTree(model).query(model, k=2)[0][:, 1]
    alone = missed[distance >= args.near_A]
    print(
        f"model nearest neighbour (median): missed {np.median(nn[missed]):.2f} Å (those with nothing near "
        f"{np.median(nn[alone]) if len(alone) else np.nan:.2f} Å), found {np.median(nn[found]):.2f} Å"
    )


if __name__ == "__main__":
    main()
