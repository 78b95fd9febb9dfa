"""INR rows of the accuracy table, for a machine with a GPU and without nerfstudio/ASE.

Reads a folder of clean projections (``clean.npz``: projections, angles_deg, pixel_size_A,
truth_A [, volume, volume_voxel_size_A]) made by ``gaussian-atoms benchmark-accuracy``, adds
the benchmark's noise (same generator and seed), fits the INR on CUDA, traces atoms and writes
one ``inr-noise{N}.json`` per noise level in the benchmark's evaluation format.

    python3 scripts/studies/inr_benchmark_rows.py FOLDER OUT --noise 50 200 500 --steps 8000
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from gaussian_atoms_method.atoms.atom_set import AtomSet  # noqa: E402
from gaussian_atoms_method.harness.evaluation import evaluate_atoms  # noqa: E402
from gaussian_atoms_method.harness.inr import fit_inr  # noqa: E402
from gaussian_atoms_method.harness.simulate import blur_and_noise  # noqa: E402
from gaussian_atoms_method.harness.tracing import trace_atoms  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("folder", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--noise", type=float, nargs="+", default=[50.0, 200.0, 500.0])
    ap.add_argument("--steps", type=int, default=10000)
    ap.add_argument("--rays", type=int, default=8192)
    ap.add_argument("--samples", type=int, default=64)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--frequency-std-per-A", type=float, default=0.35)
    ap.add_argument("--hidden", type=int, default=256)
    ap.add_argument("--density-scale", type=float, default=100.0)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--device", default="cuda")
    args = ap.parse_args()
    d = np.load(args.folder / "clean.npz")
    clean, angles, px = d["projections"], d["angles_deg"], float(d["pixel_size_A"])
    truth = AtomSet(d["truth_A"])
    volume = d["volume"].astype(np.float32) if "volume" in d else None
    args.out.mkdir(parents=True, exist_ok=True)
    for noise in args.noise:
        noisy = blur_and_noise(clean.astype(np.float64), px, 0.0, noise, args.seed + int(noise)).astype(np.float32)
        start = time.perf_counter()
        vol = fit_inr(
            noisy,
            angles,
            px,
            steps=args.steps,
            rays_per_step=args.rays,
            samples_per_ray=args.samples,
            learning_rate=args.lr,
            device=args.device,
            frequency_std_per_A=args.frequency_std_per_A,
            hidden=args.hidden,
            density_scale=args.density_scale,
        )
        idx, _ = trace_atoms(vol.data, vol.spacing_A)
        seconds = time.perf_counter() - start
        pred = AtomSet(vol.index_to_A(idx))
        pred_volume = vol.resample(volume.shape, px) if volume is not None else None
        scores = evaluate_atoms(pred, truth, reference_volume=volume, voxel_size_A=px, pred_volume=pred_volume)
        scores.update(
            seconds=seconds,
            noisy_checksum=float(noisy.astype(np.float64).sum()),
            steps=args.steps,
            settings=vars(args) | {"folder": str(args.folder), "out": str(args.out)},
        )
        (args.out / f"inr-noise{noise:g}.json").write_text(json.dumps(scores, indent=2) + "\n")
        print(
            f"noise {noise:g}: TPR {scores['tpr']:.4f} FP {scores['fp_per_true_atom']:.4f} RMSD "
            f"{scores['rmsd_pm']:.1f} pm SSIM {scores.get('ssim', float('nan')):.3f} {seconds:.0f} s checksum "
            f"{scores['noisy_checksum']:.6e}",
            flush=True,
        )


if __name__ == "__main__":
    main()
