"""Tune the INR baseline: fit it with several settings to one tilt series and print a table.

Needs torch, numpy, scipy and scikit-image only (runs on the lent GPU machine without
nerfstudio or ASE).  The truth comes from ``truth_A.npy`` beside the tilt series, or its
truth file.

    python3 scripts/studies/inr_tune.py DATA_DIR --device cuda --configs "steps=1500 rays=1024 hidden=64 scale=1"
    "hidden=512"
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from dataparsers.tilt_series_format import load_tilt_series  # noqa: E402
from gaussian_atoms_method.atoms.matching import score_atoms  # noqa: E402
from gaussian_atoms_method.harness.inr import fit_inr  # noqa: E402
from gaussian_atoms_method.harness.tracing import trace_atoms  # noqa: E402

KEYS = {
    "steps": ("steps", int),
    "rays": ("rays_per_step", int),
    "samples": ("samples_per_ray", int),
    "fstd_per_A": ("frequency_std_per_A", float),
    "hidden": ("hidden", int),
    "layers": ("layers", int),
    "lr": ("learning_rate", float),
    "scale": ("density_scale", float),
}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("data", type=Path)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--configs", nargs="+", default=["steps=1500"])
    ap.add_argument("--output", type=Path, default=None, help="JSON lines of the results")
    args = ap.parse_args()
    series = load_tilt_series(args.data)
    truth_npy = args.data / "truth_A.npy"
    if truth_npy.is_file():
        truth = np.load(truth_npy)
    else:
        from gaussian_atoms_method.atoms.atom_set import read_atoms

        truth = read_atoms(series.truth_path).positions
    print(
        "| settings | TPR | FP/atom | RMSD pm | predicted | seconds |\n| --- | --- | --- | --- | --- | --- |",
        flush=True,
    )
    for config in args.configs:
        kwargs = {KEYS[k][0]: KEYS[k][1](v) for k, v in (item.split("=") for item in config.split())}
        start = time.perf_counter()
        vol = fit_inr(
            series.projections,
            series.angles_deg,
            series.pixel_size_A,
            series.tilt_axis,
            series.centre_px,
            device=args.device,
            **kwargs,
        )
        idx, _ = trace_atoms(vol.data, vol.spacing_A)
        seconds = time.perf_counter() - start
        scores = score_atoms(vol.index_to_A(idx) + series.origin_A, truth)
        print(
            f"| {config} | {scores['tpr']:.4f} | {scores['fp_per_true_atom']:.4f} | {scores['rmsd_pm']:.1f} | "
            f"{scores['n_pred']} | {seconds:.0f} |",
            flush=True,
        )
        if args.output:
            with open(args.output, "a") as f:
                f.write(json.dumps({"config": config, "seconds": seconds, **scores}) + "\n")


if __name__ == "__main__":
    main()
