"""The paper's accuracy table: particles x tilt schemes x noise levels x methods.

For each particle and tilt scheme the clean Lobato projections are simulated once; each noise
level adds its own Gaussian noise.  Every method reads the same tilt-series directory and is
scored by the same code (:mod:`.evaluation`).  Finished runs are skipped, so an interrupted
benchmark resumes.  Results: ``results.csv``, ``results.md`` and PNG figures.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gaussian_atoms_method.harness.benchmark_options import AccuracyOptions

FIELDS = [
    "particle",
    "atoms",
    "tilts",
    "noise_std",
    "peak_to_noise",
    "method",
    "tpr",
    "fp_per_true_atom",
    "rmsd_pm",
    "ssim",
    "n_pred",
    "seconds",
    "machine",
]


@dataclass
class AccuracyBenchmark(AccuracyOptions):
    """The table (:class:`~.benchmark_options.AccuracyOptions`: its cells), with what only the
    harness sets."""

    scale: float = 1.0
    """Particle size relative to the paper's (atom count ~ scale^3)."""
    sart_iterations: int = 1
    inr_steps: int = 10000
    blur_sigma_A: float = 0.5
    seed: int = 0

    # ------------------------------------------------------------------ data
    def dataset(self, particle: str, tilts: str, noise: float) -> Path:
        """The tilt-series directory for one cell of the table (simulated once, then reused)."""
        from dataparsers.tilt_series_format import update_manifest, write_tilt_series
        from gaussian_atoms_method.harness.particles import make_particle
        from gaussian_atoms_method.harness.simulate import (
            blur_and_noise,
            parse_tilts,
            simulate_tilt_series,
            true_potential_volume,
        )

        out = (
            self.output
            / "data"
            / f"{particle}-{tilts}-{'counts' if self.noise_kind == 'poisson' else 'noise'}{noise:g}"
        )
        if (out / "tilt_series.json").is_file() and "volume" in json.loads((out / "tilt_series.json").read_text()):
            return out
        clean_path = self.output / "data" / f"{particle}-{tilts}-clean.npz"
        atoms = make_particle(particle, self.scale, self.seed)
        angles = parse_tilts(tilts)
        if clean_path.is_file():
            clean = np.load(clean_path)["projections"]
        else:
            # Blurred, noise-free projections, computed once per particle and tilt scheme.
            clean = simulate_tilt_series(
                atoms, angles, "lobato", self.pixel_size_A, blur_sigma_A=self.blur_sigma_A, noise_std=0.0
            ).projections
            clean_path.parent.mkdir(parents=True, exist_ok=True)
            np.savez(clean_path, projections=clean)
        if self.noise_kind == "poisson":
            rng = np.random.default_rng(self.seed + int(noise))
            noisy = rng.poisson(1.0 + noise * np.clip(clean, 0.0, None) / clean.max()).astype(np.float64)
            peak_to_noise = float(np.sqrt(noise))
        else:
            noisy = blur_and_noise(clean.astype(np.float64), self.pixel_size_A, 0.0, noise, self.seed + int(noise))
            peak_to_noise = float(clean.max() / noise)
        write_tilt_series(
            out,
            noisy.astype(np.float32),
            angles,
            self.pixel_size_A,
            truth=atoms,
            extra={
                "simulation": {
                    "particle": particle,
                    "scale": self.scale,
                    "potential": "lobato",
                    "noise_std": noise,
                    "noise_kind": self.noise_kind,
                    "peak_to_noise": peak_to_noise,
                    "blur_sigma_A": self.blur_sigma_A,
                }
            },
        )
        volume_path = self.output / "data" / f"{particle}-volume.npy"
        if not volume_path.is_file():
            np.save(
                volume_path,
                true_potential_volume(atoms, "lobato", self.pixel_size_A, clean.shape[1], 0.35, self.blur_sigma_A),
            )
        (out / "potential_volume.npy").unlink(missing_ok=True)
        (out / "potential_volume.npy").symlink_to(volume_path.resolve())
        update_manifest(out, volume="potential_volume.npy", volume_voxel_size_A=self.pixel_size_A)
        return out

    # ------------------------------------------------------------------ methods
    def run_method(self, method: str, data: Path) -> dict:
        run_dir = self.output / "runs" / data.name / method
        result = run_dir / "evaluation.json"
        if result.is_file():
            return json.loads(result.read_text())
        run_dir.mkdir(parents=True, exist_ok=True)
        if method in ("fbp", "sart", "inr"):
            from gaussian_atoms_method.harness.baselines import run_baseline

            run_baseline(
                data,
                run_dir,
                method,
                sart_iterations=self.sart_iterations,
                inr_steps=self.inr_steps,
                device=self.device,
            )
        elif method == "ours":
            self._run_ours(data, run_dir)
        else:
            raise ValueError(f"unknown method {method!r}; expected fbp, sart, inr or ours")
        return json.loads(result.read_text())

    def _run_ours(self, data: Path, run_dir: Path, extra_args: tuple[str, ...] = ()) -> None:
        """Our training on ``data`` (``extra_args``: trainer/model flags), scored."""
        from gaussian_atoms_method.harness.evaluation import evaluate_atoms, load_reference

        atoms, seconds = train_ours(data, run_dir, self.iterations, self.device, extra_args)
        series, truth, volume, voxel = load_reference(data)
        scores = evaluate_atoms(atoms, truth, reference_volume=volume, voxel_size_A=voxel, origin_A=series.origin_A)
        scores["seconds"] = seconds  # includes about 15 s of nerfstudio start-up
        (run_dir / "evaluation.json").write_text(json.dumps(scores, indent=2) + "\n")

    # ------------------------------------------------------------------ table
    def run(self) -> list[dict]:
        rows = []
        for particle in self.particles:
            for tilts in self.tilts:
                for noise in self.noise:
                    data = self.dataset(particle, tilts, noise)
                    sim = json.loads((data / "tilt_series.json").read_text())["simulation"]
                    for method in self.methods:
                        s = self.run_method(method, data)
                        row = {
                            "particle": particle,
                            "atoms": s["n_true"],
                            "tilts": tilts,
                            "noise_std": noise,
                            "peak_to_noise": round(sim["peak_to_noise"], 1),
                            "method": method,
                            "tpr": s["tpr"],
                            "fp_per_true_atom": s["fp_per_true_atom"],
                            "rmsd_pm": s["rmsd_pm"],
                            "ssim": s.get("ssim", float("nan")),
                            "n_pred": s["n_pred"],
                            "seconds": s.get("seconds", float("nan")),
                            "machine": s.get("machine", "this machine's CPU"),
                        }
                        rows.append(row)
                        print(
                            f"{particle} {tilts} noise {noise:g} {method}: TPR {row['tpr']:.4f} FP "
                            f"{row['fp_per_true_atom']:.4f} RMSD {row['rmsd_pm']:.1f} pm SSIM {row['ssim']:.3f} "
                            f"{row['seconds']:.0f} s",
                            flush=True,
                        )
                        self.write(rows)
        return rows

    def write(self, rows: list[dict]) -> None:
        self.output.mkdir(parents=True, exist_ok=True)
        with open(self.output / "results.csv", "w", newline="") as f:
            writer = csv.DictWriter(f, FIELDS)
            writer.writeheader()
            writer.writerows(rows)
        (self.output / "results.md").write_text(markdown_table(rows))
        plot(rows, self.output)


def train_ours(
    data: Path,
    run_dir: Path,
    iterations: int = 3000,
    device: str = "cpu",
    extra_args: tuple[str, ...] = (),
    threads: int | None = None,
    launcher: str = "gaussian-atoms",
):
    """Train on a tilt-series directory in a subprocess: ``gaussian-atoms train`` (the default)
    or ``ns-train gaussian-atoms`` (``launcher="ns-train"``; same trainer and options, a longer
    start-up).  With ``threads``, its OpenMP threads are limited to that many.

    Returns the predicted :class:`~.atoms.AtomSet` (read from the run's ``atoms.xyz``) and the
    wall time in seconds, start-up included; the run's output is kept in ``run_dir/train.log``.
    A previous run in ``run_dir`` (its fixed name) is removed first: its snapshots' times would
    otherwise be read as this run's (a rerun of ``benchmark`` into the same output scored both).
    """
    from gaussian_atoms_method.atoms.atom_set import read_atoms

    if launcher == "gaussian-atoms":
        command = [sys.executable, "-m", "gaussian_atoms_method.cli", "train"]
    elif launcher == "ns-train":
        command = [str(Path(sys.executable).parent / "ns-train"), "gaussian-atoms"]
    else:
        raise ValueError(f"launcher must be 'gaussian-atoms' or 'ns-train', got {launcher!r}")
    shutil.rmtree(run_dir / "ours" / "gaussian-atoms" / "run", ignore_errors=True)
    start = time.perf_counter()
    cmd = [
        *command,
        "--machine.device-type",
        device,
        "--vis",
        "tensorboard",
        "--output-dir",
        str(run_dir),
        "--experiment-name",
        "ours",
        "--timestamp",
        "run",
        "--max-num-iterations",
        str(iterations),
        *extra_args,
        "tilt-series",
        "--data",
        str(data),
    ]
    env = None if threads is None else {**os.environ, "OMP_NUM_THREADS": str(threads)}
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    seconds = time.perf_counter() - start
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "train.log").write_text(proc.stdout + proc.stderr)  # what the run read and chose
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(command[-2:])} failed on {data}:\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}")
    return read_atoms(run_dir / "ours" / "gaussian-atoms" / "run" / "atoms.xyz"), seconds


def scored_run(
    result: Path, run_dir: Path, prepare, score, iterations: int, device: str, flags: tuple[str, ...] = ()
) -> dict:
    """Our run's scores, kept in ``result`` and read back on a rerun (resumable benchmarks):
    otherwise ``prepare()`` writes the tilt-series directory, :func:`train_ours` fits it in
    ``run_dir`` and ``score(data, atoms)`` scores the atoms (the wall time is added)."""
    if not result.is_file():
        data = prepare()
        atoms, seconds = train_ours(data, run_dir, iterations, device, flags)  # makes run_dir
        result.write_text(json.dumps(score(data, atoms) | {"seconds": seconds}, indent=2) + "\n")
    return json.loads(result.read_text())


def markdown_table(rows: list[dict]) -> str:
    head = (
        "| particle | atoms | tilts | noise | PNR | method | TPR | FP/atom | RMSD (pm) | SSIM | predicted | time (s) "
        "| where |\n"
    )
    head += "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |\n"
    body = "".join(
        f"| {r['particle']} | {r['atoms']} | {r['tilts']} | {r['noise_std']:g} | {r['peak_to_noise']} | {r['method']} "
        f"| "
        f"{r['tpr']:.4f} | {r['fp_per_true_atom']:.4f} | {r['rmsd_pm']:.1f} | {r['ssim']:.3f} | {r['n_pred']} | "
        f"{r['seconds']:.0f} | {r['machine']} |\n"
        for r in rows
    )
    return head + body


def plot(rows: list[dict], output: Path) -> None:
    """TPR, false positives per atom and RMSD against noise, one panel row per particle/tilts."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = sorted({(r["particle"], r["tilts"]) for r in rows})
    fig, axes = plt.subplots(len(groups), 3, figsize=(12, 3.2 * len(groups)), squeeze=False)
    for g, (particle, tilts) in enumerate(groups):
        for method in sorted({r["method"] for r in rows}):
            sel = sorted(
                (r for r in rows if (r["particle"], r["tilts"], r["method"]) == (particle, tilts, method)),
                key=lambda r: r["noise_std"],
            )
            noise = [r["noise_std"] for r in sel]
            for k, key in enumerate(("tpr", "fp_per_true_atom", "rmsd_pm")):
                axes[g, k].plot(noise, [r[key] for r in sel], "o-", label=method)
        for k, label in enumerate(("TPR", "false positives per atom", "RMSD (pm)")):
            axes[g, k].set_title(f"{particle}, {tilts}: {label}")
            axes[g, k].set_xlabel("noise std (V·Å)")
        axes[g, 0].legend()
    fig.tight_layout()
    fig.savefig(output / "accuracy_vs_noise.png", dpi=100)
    plt.close(fig)
