"""What a kernel applied to the detector alone misses at a film's edge: a replica's true atoms drawn
as the fit draws atoms (one Gaussian, the 1, 2, 4 Å kernel; the weights fitted by non-negative least
squares) on a detector widened by 0 to N pixels, blurred and cut back, against the replica's
noise-free views; and, for fitted runs, each found atom's error by its distance to the field's edge.

    python scripts/studies/field_edge_kernel.py --data REPLICA [--sigma-A 0.55] [--runs RUN_DIR ...]

``REPLICA``: ``gaussian-atoms simulate --like DIR --output REPLICA`` (it keeps ``noise.npy``).
``RUN_DIR``: a run's directory on it (``atoms.xyz``).
"""

from __future__ import annotations

import argparse
import copy
from pathlib import Path

import numpy as np


def misfit_by_margin(series, truth, noise, sigma_A: float, margins) -> None:
    from scipy.optimize import nnls

    from gaussian_atoms_method.atoms.atom_set import AtomSet
    from gaussian_atoms_method.atoms.view_prediction import predicted_views

    clean = np.asarray(series.projections, float) - noise
    v, h, w = clean.shape
    views = np.arange(0, v, 3)
    edge = np.ones((h, w), bool)
    edge[12 : h - 12, 12 : w - 12] = False
    amp = np.ones(len(truth)) / (2 * np.pi * sigma_A**2) ** 1.5
    atoms = AtomSet(positions=truth.positions, sigmas=np.full(len(truth), sigma_A), amplitudes=amp)
    print("| margin (px) | misfit / noise, interior | misfit / noise, 12 px at the edge | weights: atom, 1, 2, 4 Å |")
    print("| --- | --- | --- | --- |")
    for pad in margins:
        wide = copy.copy(series)
        wide.projections = np.zeros((v, h + 2 * pad, w + 2 * pad), np.float32)
        wide.centre_px = (series.centre_px[0] + pad, series.centre_px[1] + pad)
        basis = [
            predicted_views(atoms, wide, k)[views][:, pad : pad + h, pad : pad + w]
            for k in (None, (1.0, 0, 0), (0, 1.0, 0), (0, 0, 1.0))
        ]
        a = np.stack([b.ravel() for b in basis] + [np.ones(basis[0].size)], 1)
        x, _ = nnls(a, clean[views].ravel())
        r = (clean[views].ravel() - a @ x).reshape(len(views), h, w)
        n, share = noise[views].std(), np.round(x[:4] / x[:4].sum(), 3)
        print(f"| {pad} | {r[:, ~edge].std() / n:.2f} | {r[:, edge].std() / n:.2f} | {share} |")


def errors_by_edge(series, truth, run: Path) -> None:
    from gaussian_atoms_method.atoms.atom_set import read_atoms
    from gaussian_atoms_method.atoms.matching import global_shift, match_atoms

    atoms = read_atoms(run / "atoms.xyz")
    shift = global_shift(atoms.positions, truth.positions)
    pi, ti = match_atoms(atoms.positions + shift, truth.positions, 0.75)
    e = atoms.positions[pi] + shift - truth.positions[ti]
    p = truth.positions[ti] - np.asarray(series.origin_A)
    h, w = series.projections.shape[1:]
    row, col = p[:, 0] / series.pixel_size_A + series.centre_px[0], p[:, 1] / series.pixel_size_A + series.centre_px[1]
    edge_A = np.minimum.reduce([row, h - 1 - row, col, w - 1 - col]) * series.pixel_size_A
    cells = [f"{np.sqrt((e[m] ** 2).sum(1).mean()) * 100:.1f} ({m.sum()})" for m in
             (edge_A < 3, (edge_A >= 3) & (edge_A < 6), edge_A >= 6, np.ones(len(e), bool))]  # fmt: skip
    print(f"| {run} | {len(pi)} | " + " | ".join(cells) + " |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--sigma-A", type=float, default=0.55, help="the atoms' width in the fit's model, Å")
    parser.add_argument("--margins", type=int, nargs="+", default=[0, 3, 6, 9, 12])
    parser.add_argument("--runs", type=Path, nargs="*", default=[])
    args = parser.parse_args()

    from dataparsers.tilt_series_format import load_tilt_series
    from gaussian_atoms_method.atoms.atom_set import read_atoms

    series = load_tilt_series(args.data)
    truth = read_atoms(series.truth_path)
    misfit_by_margin(series, truth, np.load(args.data / "noise.npy"), args.sigma_A, args.margins)
    if args.runs:
        print("\n| run | found | RMSD (pm), atoms within 3 Å of the edge | 3-6 Å | beyond 6 Å | all |")
        print("| --- | --- | --- | --- | --- | --- |")
        for run in args.runs:
            errors_by_edge(series, truth, run)


if __name__ == "__main__":
    main()
