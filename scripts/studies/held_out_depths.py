"""Do the views a fit never saw put our misplaced Ta atoms where we do, or where the model does?

A fit of one half of a Ta sub-area's views (``gaussian-atoms held-out-views`` writes the two
halves and fits them) is matched to the authors' model in the scored region, after the
benchmark's global shift.  Its extra atoms beside exactly one missed model atom (within
``--near-A``) are the same atom placed elsewhere (``film_misses.py``).  Each is moved alone to
the model's place, and the cost is read on the views it was fitted to and on the half it never
saw (:func:`gaussian_atoms_method.harness.held_out.move_costs`).  As a control, matched atoms are
moved by the same offsets.  With ``--taken-out``, each atom in the region is also taken out alone
(moved out of every view), matched and unmatched apart: a Gaussian the unseen views do not need
costs them nothing to lose.

    python scripts/studies/held_out_depths.py --views outputs/held-out-23/views \\
        --runs outputs/held-out-23/runs/learned --area 23 --interior-px 10 4
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--views", type=Path, required=True, help="held-out-views' views folder (even, odd)")
    parser.add_argument("--runs", type=Path, required=True, help="held-out-views' runs folder of one kernel")
    parser.add_argument("--area", type=int, required=True)
    parser.add_argument("--film", type=Path, default=Path("../shared/data/ta_film"), help="the film's folder")
    parser.add_argument("--kernel", default="0,0,0", help="the runs' kernel: intensity fractions at 1, 2, 4 Å")
    parser.add_argument("--interior-px", type=int, nargs=2, default=(0, 0), help="rows and columns left out")
    parser.add_argument("--near-A", type=float, default=1.5, help="an extra atom this close to a missed one is it")
    parser.add_argument("--controls", type=int, default=60, help="matched atoms moved as a control")
    parser.add_argument(
        "--taken-out", action="store_true", help="also take each atom in the region out alone (matched or not)"
    )
    args = parser.parse_args()
    try:
        report(args)
    except (OSError, ValueError) as err:  # a missing run or file, a series that cannot be read
        raise SystemExit(f"held_out_depths.py: {err}") from None


def report(args) -> None:
    """Print the study's tables for the parsed command line."""
    from dataparsers.tilt_series_format import load_tilt_series
    from gaussian_atoms_method.atoms.atom_set import read_atoms
    from gaussian_atoms_method.atoms.view_prediction import run_gaussians
    from gaussian_atoms_method.harness import film_benchmark as fb
    from gaussian_atoms_method.harness.held_out import move_costs

    model = fb.model_in_area_A(args.film, args.area)
    kernel = [float(v) for v in args.kernel.split(",")]
    rng = np.random.default_rng(0)
    rows = [
        "| fit | moved | atoms | cost on fitted views (median) | on unseen views (median) | "
        "unseen views prefer the move |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for half, other in (("even", "odd"), ("odd", "even")):
        fitted, held = load_tilt_series(args.views / half), load_tilt_series(args.views / other)
        centre = tuple(json.loads((args.views / half / "tilt_series.json").read_text())["centre_px"])
        run = args.runs / half / "ours" / "gaussian-atoms" / "run"
        reported, gaussians = read_atoms(run / "atoms.xyz"), run_gaussians(run)  # atoms.xyz comes first
        box, inside = fb.scored_region(model, fitted.projections.shape[1:], centre)
        pred, shift, matched, in_box, missed, extra = fb.misses_and_extras(reported.positions, model, box, inside)
        count, partner = fb.missed_nearby(pred, model, missed, extra, args.near_A)
        moved, targets = extra[count == 1], model[partner[count == 1]] - shift
        offsets = targets - reported.positions[moved]
        controls = (
            rng.choice(np.flatnonzero(matched & in_box), size=min(args.controls, int((matched & in_box).sum())))
            if len(moved)
            else np.zeros(0, dtype=np.int64)
        )
        control_targets = reported.positions[controls] + offsets[np.arange(len(controls)) % max(len(offsets), 1)]
        groups = [
            ("misplaced, to the model's place", moved, targets),
            ("matched, by the same offsets", controls, control_targets),
        ]
        if args.taken_out:  # out of every view: far along the tilt axis
            for label, sel in (("matched, taken out", matched & in_box), ("unmatched, taken out", ~matched & in_box)):
                idx = np.flatnonzero(sel)
                groups.append((label, idx, reported.positions[idx] + np.array([0.0, 1e4, 0.0])))
        groups = [g for g in groups if len(g[1])]
        if not groups:
            continue
        # one call for every group: the views' residuals are rendered once a half
        cost = move_costs(
            gaussians,
            np.concatenate([g[1] for g in groups]),
            np.concatenate([g[2] for g in groups]),
            fitted,
            held,
            kernel,
            tuple(args.interior_px),
        )
        ends = np.cumsum([len(g[1]) for g in groups])
        for (label, _, _), part in zip(groups, np.split(cost, ends[:-1])):
            rows.append(
                f"| {half} | {label} | {len(part)} | {np.median(part[:, 0]):.3g} | {np.median(part[:, 1]):.3g} | "
                f"{int((part[:, 1] < 0).sum())} |"
            )
    print("\n".join(rows))  # once both halves are read: nothing printed for a run that fails


if __name__ == "__main__":
    main()
