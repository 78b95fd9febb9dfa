"""Does fitting several views per step converge faster per second than one?

ns-train renders one view per step.  A GPU renders all 47 views of the Au series in one
batched projection for about 7x the time of one (docs/performance.md, projectors), so a batch
might buy more accuracy per second; on a CPU the cost grows with the views.  This measures it
on the fit itself, outside nerfstudio: the same start as the model (back-projection
candidates, masses by the back-projection), the same Adam learning rates (in Å), L1 on ``B``
views per step (a fresh random order of the views each pass), for a fixed wall time.  There is
no densify / prune / merge during the fit; each snapshot is pruned as the model prunes (mass
below 0.25 of the typical atom's, or wider than 1.5 Å) and scored against the truth.

    python scripts/studies/batched_views.py DATA --device cuda --batches 1 4 16 47 --seconds 20

Prints one Markdown row per snapshot (batch, seconds of fitting, steps, views seen, TPR, FP
per atom, RMSD) and writes batched_views.csv to --output.
"""

from __future__ import annotations

import argparse
import csv
import math
import time
from pathlib import Path

import numpy as np
import torch

from gaussian_atoms_method.atoms.candidates import backprojection_candidates
from gaussian_atoms_method.atoms.matching import score_atoms
from gaussian_atoms_method.harness.evaluation import load_reference
from gaussian_atoms_method.physics.geometry import detector_axes_from_tilts, pixel_centres
from gaussian_atoms_method.physics.projector import (
    gaussian_mass,
    project_gaussians,
    project_gaussians_tiled,
    typical_mass,
)


def pruned(means, sigmas, amplitudes, max_sigma_A=1.5, fraction=0.25) -> np.ndarray:
    """Positions kept by the model's prune rule (mass-weighted median mass of atom-like widths)."""
    mass = gaussian_mass(sigmas, amplitudes)
    atom_like = sigmas <= max_sigma_A
    keep = (mass >= fraction * typical_mass(mass[atom_like])) & atom_like
    return means[keep].detach().cpu().double().numpy()


def fit(series, truth, batch: int, seconds: float, every: float, device: str, seed: int = 0) -> list[dict]:
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    projections = torch.as_tensor(np.asarray(series.projections), dtype=torch.float32, device=device)
    n_views, h, w = projections.shape
    axes = torch.as_tensor(
        detector_axes_from_tilts(series.angles_deg, series.tilt_axis), dtype=torch.float32, device=device
    )
    ci, cj = ((h - 1) / 2, (w - 1) / 2) if series.centre_px is None else series.centre_px
    rows = torch.as_tensor(pixel_centres(h, series.pixel_size_A, ci), dtype=torch.float32, device=device)
    cols = torch.as_tensor(pixel_centres(w, series.pixel_size_A, cj), dtype=torch.float32, device=device)
    positions, values = backprojection_candidates(
        series.projections,
        series.angles_deg,
        series.pixel_size_A,
        series.tilt_axis,
        series.centre_px,
        10000,
        device=device,
        return_values=True,
    )
    weights = np.clip(values, 0.01 * values.max(), None)
    weights = weights / weights.mean()
    sigma0 = 0.7
    mass = float(projections.double().sum(dim=(-2, -1)).mean()) * series.pixel_size_A**2
    amp0 = mass / len(positions) / (2 * math.pi * sigma0**2) ** 1.5
    means = torch.nn.Parameter(torch.as_tensor(positions, dtype=torch.float32, device=device))
    log_sigmas = torch.nn.Parameter(torch.full((len(positions),), math.log(sigma0), device=device))
    log_amps = torch.nn.Parameter(torch.as_tensor(np.log(amp0 * weights), dtype=torch.float32, device=device))
    length_A = max(h, w) * series.pixel_size_A  # the model's normalised unit
    optimiser = torch.optim.Adam(
        [
            {"params": [means], "lr": 1e-3 * length_A},
            {"params": [log_sigmas], "lr": 5e-3},
            {"params": [log_amps], "lr": 2e-2},
        ],
        eps=1e-15,
    )
    project = project_gaussians if device == "cuda" else project_gaussians_tiled
    floor = math.log(0.15)
    out, order, steps, seen = [], [], 0, 0
    elapsed, next_snapshot = 0.0, every
    while elapsed < seconds:
        if device == "cuda":
            torch.cuda.synchronize()
        start = time.perf_counter()
        if len(order) < batch:
            order += list(rng.permutation(n_views))
        views, order = order[:batch], order[batch:]
        idx = torch.as_tensor(views, device=device)
        sig = torch.exp(log_sigmas.clamp_min(floor))
        image = project(means, sig, torch.exp(log_amps), axes[idx], rows, cols)
        loss = (image - projections[idx]).abs().mean()
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        optimiser.step()
        with torch.no_grad():
            log_sigmas.clamp_(math.log(0.15), math.log(5.0))
        if device == "cuda":
            torch.cuda.synchronize()
        elapsed += time.perf_counter() - start  # fitting time only: scoring is not counted
        steps, seen = steps + 1, seen + batch
        if elapsed >= next_snapshot or elapsed >= seconds:
            with torch.no_grad():
                kept = pruned(means, torch.exp(log_sigmas), torch.exp(log_amps))
            s = score_atoms(kept + series.origin_A, truth.positions)
            out.append(
                {
                    "batch": batch,
                    "seconds": round(elapsed, 2),
                    "steps": steps,
                    "views": seen,
                    "tpr": s["tpr"],
                    "fp_per_true_atom": s["fp_per_true_atom"],
                    "rmsd_pm": s["rmsd_pm"],
                }
            )
            r = out[-1]
            print(
                f"| {batch} | {r['seconds']:.1f} | {steps} | {seen} | {r['tpr']:.4f} | {r['fp_per_true_atom']:.4f} | "
                f"{r['rmsd_pm']:.1f} |",
                flush=True,
            )
            next_snapshot += every
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data", type=Path)
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 4, 16, 47])
    parser.add_argument("--seconds", type=float, default=20.0, help="fitting time per batch size")
    parser.add_argument("--every", type=float, default=2.0, help="seconds of fitting between snapshots")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu", choices=["cpu", "cuda"])
    parser.add_argument("--output", type=Path, default=Path("outputs/batched-views"))
    args = parser.parse_args()
    torch.backends.cuda.matmul.allow_tf32 = False  # 0.6% projector error with TF32
    series, truth, _, _ = load_reference(args.data)
    if args.device == "cuda":  # CUDA and cuBLAS start-up outside the timed fits
        x = torch.ones(8, 3, device="cuda", requires_grad=True)
        project_gaussians(
            x,
            torch.ones(8, device="cuda"),
            torch.ones(8, device="cuda"),
            torch.eye(3, device="cuda")[None],
            torch.zeros(4, device="cuda"),
            torch.zeros(4, device="cuda"),
        ).sum().backward()
    print(
        f"{args.device}: {series.projections.shape[0]} views of {series.projections.shape[1]} x "
        f"{series.projections.shape[2]}, {len(truth.positions)} atoms\n"
    )
    print("| views per step | fitting time (s) | steps | views seen | TPR | FP/atom | RMSD (pm) |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    rows = [r for b in args.batches for r in fit(series, truth, b, args.seconds, args.every, args.device)]
    args.output.mkdir(parents=True, exist_ok=True)
    with open(args.output / "batched_views.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


if __name__ == "__main__":
    main()
