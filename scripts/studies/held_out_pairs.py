"""Do the views a fit never saw demand its close pairs?  Merge costs on fitted and held-out views.

A fit of the even views of a series (``gaussian-atoms held-out-views`` writes the two halves and fits them)
is read with every Gaussian; for its close pairs, and for a sample of pairs at first-shell
distances, merging the pair into one Gaussian is scored on the views it was fitted to and on the
odd views it never saw (:func:`gaussian_atoms_method.harness.held_out.pair_merge_costs`).  A pair
the data demand keeps its cost on the unseen views, as pairs of real neighbours do; one that
only fits the fitted views' own errors loses it.  Prints a table by distance.

    python scripts/studies/held_out_pairs.py --run RUN_DIR --fitted VIEWS/even --held VIEWS/odd \\
        --kernel 0,0.3,0 --interior-px 10 4
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--run", type=Path, required=True, help="the run directory of a fit of --fitted (atoms.xyz, non_atoms.xyz)"
    )
    parser.add_argument("--fitted", type=Path, required=True, help="the tilt series the run was fitted to")
    parser.add_argument("--held", type=Path, required=True, help="a tilt series of views the run never saw")
    parser.add_argument("--kernel", default="0,0,0", help="the run's kernel: intensity fractions at 1, 2, 4 Å")
    parser.add_argument(
        "--interior-px", type=int, nargs=2, default=(0, 0), help="rows and columns left out at each detector edge"
    )
    parser.add_argument(
        "--bins-A", type=float, nargs="+", default=[0.0, 1.5, 2.0, 2.6, 3.2], help="distance bins of the pairs, Å"
    )
    parser.add_argument("--per-bin", type=int, default=300, help="at most this many pairs a bin (a random sample)")
    args = parser.parse_args()

    from scipy.spatial import cKDTree

    from dataparsers.tilt_series_format import load_tilt_series
    from gaussian_atoms_method.atoms.view_prediction import run_gaussians
    from gaussian_atoms_method.harness.held_out import pair_merge_costs

    try:
        fitted, held = load_tilt_series(args.fitted), load_tilt_series(args.held)
        atoms = run_gaussians(args.run)
        kernel = [float(v) for v in args.kernel.split(",")]
    except (OSError, ValueError) as err:
        raise SystemExit(f"held_out_pairs: {err}") from None
    pairs = cKDTree(atoms.positions).query_pairs(max(args.bins_A), output_type="ndarray")
    distance = np.linalg.norm(atoms.positions[pairs[:, 0]] - atoms.positions[pairs[:, 1]], axis=1)
    rng = np.random.default_rng(0)
    print(
        "| pairs (Å) | pairs scored | cost on fitted views (median) | on held-out views (median) | held-out / fitted "
        "(median) | held-out prefers one Gaussian |"
    )
    print("| --- | --- | --- | --- | --- | --- |")
    for lo, hi in zip(args.bins_A[:-1], args.bins_A[1:]):
        idx = np.nonzero((distance >= lo) & (distance < hi))[0]
        if len(idx) == 0:
            continue
        idx = rng.choice(idx, min(len(idx), args.per_bin), replace=False)
        costs = pair_merge_costs(atoms, pairs[idx], fitted, held, kernel, tuple(args.interior_px))
        ratio = costs[:, 1] / np.where(costs[:, 0] > 0, costs[:, 0], np.nan)
        print(
            f"| {lo:g}-{hi:g} | {len(idx)} | {np.median(costs[:, 0]):.3g} | {np.median(costs[:, 1]):.3g} | "
            f"{np.nanmedian(ratio):.2f} | {np.mean(costs[:, 1] < 0):.2f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
