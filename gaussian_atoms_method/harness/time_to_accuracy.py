"""Time to accuracy: our method evaluated during training against FBP and SART with tracing,
on the same data in the same run (``gaussian-atoms benchmark``).

Ours runs as ``gaussian-atoms train`` (or ``ns-train gaussian-atoms``: ``launcher``) with
``--pipeline.model.snapshot-every K``: every K steps the model writes its current atoms and
the wall-clock time; each snapshot is scored against the truth, so every row is (seconds since
the training process was launched, TPR, FP per atom, RMSD).  Launch time counts (nerfstudio's
start-up and our back-projection start are part of what a user waits for).  FBP and SART (one
sweep) are timed from reading the data to traced atoms.  Peak memory: the largest resident set of the training process (CPU) and the GPU's
largest allocation when on CUDA.
"""

from __future__ import annotations

import csv
import resource
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

FIELDS = ["method", "step", "seconds", "tpr", "fp_per_true_atom", "rmsd_pm", "n_pred", "gaussians", "peak_rss_GB", "peak_gpu_GB"]


@dataclass
class TimeToAccuracy:
    data: Path
    output: Path
    iterations: int = 3000
    snapshot_every: int = 100
    device: str = "cpu"
    baselines: tuple[str, ...] = ("fbp", "sart")
    extra_args: tuple[str, ...] = ()
    launcher: str = "gaussian-atoms"

    def run(self) -> list[dict]:
        from gaussian_atoms_method.atoms.atom_set import read_atoms
        from gaussian_atoms_method.physics.reconstruction import reconstruct
        from gaussian_atoms_method.harness.benchmark import train_ours
        from gaussian_atoms_method.harness.evaluation import load_reference
        from gaussian_atoms_method.atoms.matching import score_atoms
        from gaussian_atoms_method.harness.tracing import trace_atoms

        series, truth, _, _ = load_reference(self.data)
        # FBP runs in torch: its import (seconds) is this process's start-up, not the baseline's.
        import torch  # noqa: F401

        rows = []
        for method in self.baselines:
            start = time.perf_counter()
            vol = reconstruct(series.projections, series.angles_deg, series.pixel_size_A, method, series.tilt_axis, series.centre_px, tilt_axis_angle_deg=series.tilt_axis_angle_deg)
            idx, _ = trace_atoms(vol.data, vol.spacing_A)
            seconds = time.perf_counter() - start
            s = score_atoms(vol.index_to_A(idx) + series.origin_A, truth.positions)
            rows.append(self._row(method, "", seconds, s, rss_gb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6))
            print(self._line(rows[-1]), flush=True)
        run_dir = self.output / "run"
        launch = time.time()
        train_ours(self.data, run_dir, self.iterations, self.device, ("--pipeline.model.snapshot-every", str(self.snapshot_every), *self.extra_args), launcher=self.launcher)
        rss_gb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1e6
        snapshots = run_dir / "ours" / "gaussian-atoms" / "run" / "snapshots"
        times = np.loadtxt(snapshots / "times.csv", delimiter=",", ndmin=2)
        for step, stamp, gaussians, gpu_bytes in times:
            atoms = read_atoms(snapshots / f"step-{int(step):06d}.csv")
            s = score_atoms(atoms.positions, truth.positions)
            rows.append(self._row("ours", int(step), stamp - launch, s, gaussians=int(gaussians), rss_gb=rss_gb, gpu_gb=gpu_bytes / 1e9))
            print(self._line(rows[-1]), flush=True)
        self.write(rows)
        return rows

    @staticmethod
    def _row(method, step, seconds, s, gaussians=None, rss_gb=float("nan"), gpu_gb=float("nan")) -> dict:
        return {
            "method": method, "step": step, "seconds": seconds, "tpr": s["tpr"], "fp_per_true_atom": s["fp_per_true_atom"],
            "rmsd_pm": s["rmsd_pm"], "n_pred": s["n_pred"], "gaussians": gaussians if gaussians is not None else s["n_pred"],
            "peak_rss_GB": rss_gb, "peak_gpu_GB": gpu_gb,
        }  # fmt: skip

    @staticmethod
    def _line(r: dict) -> str:
        step = f" step {r['step']}" if r["step"] != "" else ""
        return f"{r['method']}{step}: {r['seconds']:.1f} s TPR {r['tpr']:.4f} FP {r['fp_per_true_atom']:.4f} RMSD {r['rmsd_pm']:.1f} pm"

    def write(self, rows: list[dict]) -> None:
        self.output.mkdir(parents=True, exist_ok=True)
        with open(self.output / "time_to_accuracy.csv", "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=FIELDS)
            writer.writeheader()
            writer.writerows(rows)
        lines = ["| method | step | time (s) | TPR | FP/atom | RMSD (pm) | atoms | peak RSS (GB) |", "| --- | --- | --- | --- | --- | --- | --- | --- |"]
        for r in rows:
            lines.append(f"| {r['method']} | {r['step']} | {r['seconds']:.1f} | {r['tpr']:.4f} | {r['fp_per_true_atom']:.4f} | {r['rmsd_pm']:.1f} | {r['n_pred']} | {r['peak_rss_GB']:.2f} |")
        (self.output / "time_to_accuracy.md").write_text("\n".join(lines) + "\n")
        plot_time_to_accuracy(rows, self.output / "time_to_accuracy.png")


def plot_time_to_accuracy(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ours = [r for r in rows if r["method"] == "ours"]
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    for ax, key, label in zip(axes, ("tpr", "fp_per_true_atom", "rmsd_pm"), ("TPR", "false positives per atom", "RMSD (pm)")):
        ax.plot([r["seconds"] for r in ours], [r[key] for r in ours], "o-", ms=3, label="ours (during training)")
        for r, marker in zip([r for r in rows if r["method"] != "ours"], "s^v"):
            ax.plot([r["seconds"]], [r[key]], marker, ms=8, label=f"{r['method']} + tracing")
        ax.set_xlabel("wall time (s)")
        ax.set_ylabel(label)
        if key == "fp_per_true_atom":
            ax.set_yscale("symlog", linthresh=1e-3)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
