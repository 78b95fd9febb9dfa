"""Alignment refinement and background: misaligned and background-laden tilt series, with and
without the model's per-view shift and background parameters.

A small Au sphere (Lobato potentials, limited tilts, noise 50) is simulated once; then
* "shifted": every projection moved by a random in-plane shift, uniform in [-1, 1] Å per axis;
* "tilted": every projection taken at its nominal angle plus an error uniform in [-0.5, 0.5]
  degrees (the file keeps the nominal angles);
* "background": a smooth plane added to every projection (offset 10% of the peak plus a
  gradient of 10% across the detector, different per view).
Each dataset is reconstructed by ``ns-train gaussian-atoms`` with the switches off and on.

    python scripts/studies/alignment_background.py --output outputs/alignment [--radius-A 10]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from scipy import ndimage

from dataparsers.tilt_series_format import load_tilt_series, write_tilt_series
from gaussian_atoms_method.atoms.atom_set import read_atoms
from gaussian_atoms_method.harness.benchmark import train_ours
from gaussian_atoms_method.harness.evaluation import evaluate_atoms
from gaussian_atoms_method.harness.simulate import parse_tilts, simulate_tilt_series, spherical_particle

RUNS = [
    ("aligned", "aligned", ()),
    ("shifted", "no refinement", ()),
    ("shifted", "alignment refinement", ("--pipeline.model.refine-alignment", "True")),
    ("tilted", "no refinement", ()),
    ("tilted", "tilt refinement", ("--pipeline.model.refine-tilts", "True")),
    ("background", "no background model", ()),
    ("background", "plane background", ("--pipeline.model.background", "plane")),
]


def make_data(output: Path, radius_A: float, seed: int) -> dict[str, Path]:
    rng = np.random.default_rng(seed)
    atoms = spherical_particle("Au", radius_A=radius_A)
    angles = parse_tilts("limited")
    sim = simulate_tilt_series(atoms, angles, "lobato", noise_std=50.0, seed=seed)
    px = sim.pixel_size_A
    clean = sim.projections
    shifts_A = rng.uniform(-1.0, 1.0, size=(len(angles), 2))
    shifted = np.stack([ndimage.shift(p, s / px, order=3, mode="constant") for p, s in zip(clean, shifts_A)])
    n = clean.shape[1]
    r = (np.arange(n) - (n - 1) / 2) / n
    peak = float(clean.max())
    planes = [
        peak * (0.1 + 0.1 * (a * r[:, None] + b * r[None, :])) for a, b in rng.uniform(-1, 1, size=(len(angles), 2))
    ]
    background = clean + np.stack(planes)
    tilt_errors = rng.uniform(-0.5, 0.5, size=len(angles))
    tilted = simulate_tilt_series(atoms, angles + tilt_errors, "lobato", noise_std=50.0, seed=seed).projections
    out = {}
    for name, proj in (("aligned", clean), ("shifted", shifted), ("background", background), ("tilted", tilted)):
        out[name] = write_tilt_series(output / "data" / name, proj.astype(np.float32), angles, px, truth=sim.truth)
    np.save(output / "data" / "true_shifts_A.npy", shifts_A)
    np.save(output / "data" / "true_tilt_errors_deg.npy", tilt_errors)
    return out


def _learned(run_dir: Path, name: str) -> np.ndarray | None:
    ckpts = sorted((run_dir / "ours" / "gaussian-atoms" / "run" / "nerfstudio_models").glob("*.ckpt"))
    if not ckpts:
        return None
    state = torch.load(ckpts[-1], map_location="cpu", weights_only=False)["pipeline"]
    key = f"_model.view_params.{name}"
    return state[key].numpy() if key in state else None


def learned_tilt_errors_deg(run_dir: Path) -> np.ndarray | None:
    t = _learned(run_dir, "view_tilts")
    return None if t is None else np.rad2deg(t[:, 0] - t[:, 0].mean())


def learned_shifts_A(run_dir: Path, data: Path) -> np.ndarray | None:
    s = _learned(run_dir, "view_shifts")
    if s is None:
        return None
    series = load_tilt_series(data)
    length_scale = 1.0 / (max(series.image_shape) * series.pixel_size_A)
    return (s - s.mean(0)) / length_scale


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--output", type=Path, default=Path("outputs/alignment"))
    parser.add_argument("--radius-A", type=float, default=10.0)
    parser.add_argument("--iterations", type=int, default=3000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    data = make_data(args.output, args.radius_A, args.seed)
    true_shifts = np.load(args.output / "data" / "true_shifts_A.npy")
    rows = []
    for dataset, label, flags in RUNS:
        run_dir = args.output / "runs" / f"{dataset}-{label.replace(' ', '-')}"
        result = run_dir / "evaluation.json"
        if not result.is_file():
            atoms, seconds = train_ours(data[dataset], run_dir, args.iterations, "cpu", flags)
            scores = evaluate_atoms(atoms, read_atoms(data[dataset] / "atoms_true.xyz"))
            scores["seconds"] = seconds
            learned = learned_shifts_A(run_dir, data[dataset])
            if learned is not None:
                err = learned - (true_shifts - true_shifts.mean(0))
                scores["shift_error_rms_A"] = float(np.sqrt((err**2).sum(1).mean()))
            tilts = learned_tilt_errors_deg(run_dir)
            if tilts is not None:
                true_tilts = np.load(args.output / "data" / "true_tilt_errors_deg.npy")
                scores["tilt_error_rms_deg"] = float(np.sqrt(np.mean((tilts - (true_tilts - true_tilts.mean())) ** 2)))
            run_dir.mkdir(parents=True, exist_ok=True)
            result.write_text(json.dumps(scores, indent=2) + "\n")
        s = json.loads(result.read_text())
        rows.append((dataset, label, s))
        print(dataset, label, json.dumps(s), flush=True)
    lines = [
        "| data | model | TPR | FP/atom | RMSD (pm) | shift error RMS (Å) | tilt error RMS (deg) | time (s) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for dataset, label, s in rows:
        shift = f"{s['shift_error_rms_A']:.3f}" if "shift_error_rms_A" in s else "-"
        tilt = f"{s['tilt_error_rms_deg']:.3f}" if "tilt_error_rms_deg" in s else "-"
        lines.append(
            f"| {dataset} | {label} | {s['tpr']:.4f} | {s['fp_per_true_atom']:.4f} | {s['rmsd_pm']:.1f} | {shift} | "
            f"{tilt} | {s['seconds']:.0f} |"
        )
    rms_true = float(np.sqrt(((true_shifts - true_shifts.mean(0)) ** 2).sum(1).mean()))
    true_tilts = np.load(args.output / "data" / "true_tilt_errors_deg.npy")
    text = (
        f"Au sphere radius {args.radius_A} Å, limited tilts, noise 50; true shifts RMS {rms_true:.2f} Å, tilt errors "
        f"RMS {np.std(true_tilts):.2f} deg\n\n" + "\n".join(lines) + "\n"
    )
    (args.output / "results.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
