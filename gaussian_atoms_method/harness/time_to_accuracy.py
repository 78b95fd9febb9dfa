"""Time to accuracy: our method evaluated during training against the classical
reconstructions with tracing (:data:`CLASSICAL`: FBP, SART, SIRT, ASTRA's), on the same data in
the same run (``gaussian-atoms benchmark``).

Ours runs as ``gaussian-atoms train`` (or ``ns-train gaussian-atoms``: ``launcher``) with
``--pipeline.model.snapshot-every K``: every K steps the model writes its current atoms and
the wall-clock time; each snapshot is scored against the truth, so every row is (seconds since
the training process was launched, TPR, FP per atom, RMSD).  Launch time counts (nerfstudio's
start-up and our back-projection start are part of what a user waits for); what the snapshots
themselves cost the run does not (``times.csv`` records it: scoring them is the benchmark's
work, and a run without them is that much sooner).  The classical
rows are timed from the data in memory to traced atoms (:func:`classical_rows`).  Peak memory:
the largest resident set of the training process (CPU) and the GPU's largest allocation when
on CUDA.
"""

from __future__ import annotations

import csv
import resource
import time
from dataclasses import dataclass
from pathlib import Path

CLASSICAL = ("fbp", "sart", "sirt", "astra-fbp", "astra-sirt", "astra-cuda-fbp", "astra-cuda-sirt")
"""Classical reconstructions + tracing: scikit-image's FBP (our sparse-matrix form, on the run's
device) and SART (one sweep, CPU); SIRT with our FBP's sparse matrix on the run's device
(:func:`~gaussian_atoms_method.physics.reconstruction.sirt`); ASTRA's FBP and SIRT on the CPU
and with its CUDA algorithms (:mod:`.astra_rows`, optional)."""

SIRT_ITERATIONS = (10, 25, 50, 100, 200)
"""SIRT's rows by default: traced after this many iterations (each row's time is the
iterations' so far plus its own tracing), so the table shows SIRT's best, wherever it falls
(on the Au series at noise 200: 10 iterations; later ones fit the noise and trace false atoms)."""

FIELDS = [
    "method",
    "step",
    "seconds",
    "tpr",
    "fp_per_true_atom",
    "rmsd_pm",
    "n_pred",
    "gaussians",
    "peak_rss_GB",
    "peak_gpu_GB",
]


@dataclass
class TimeToAccuracy:
    data: Path
    output: Path
    iterations: int = 3000
    snapshot_every: int = 100
    device: str = "cpu"
    baselines: tuple[str, ...] = ()
    """Classical rows (:data:`CLASSICAL`); empty: :func:`default_baselines` for the device."""
    extra_args: tuple[str, ...] = ()
    launcher: str = "gaussian-atoms"
    sirt_iterations: tuple[int, ...] = SIRT_ITERATIONS
    """The iteration counts SIRT's rows are traced at."""

    def run(self) -> list[dict]:
        from gaussian_atoms_method.atoms.atom_set import read_atoms
        from gaussian_atoms_method.atoms.matching import score_atoms
        from gaussian_atoms_method.engine.results import read_snapshot_times
        from gaussian_atoms_method.harness.benchmark import train_ours
        from gaussian_atoms_method.harness.evaluation import load_reference

        series, truth, _, _ = load_reference(self.data)
        # FBP runs in torch: its import (seconds) is this process's start-up, not the baseline's.
        import torch  # noqa: F401

        rows = []
        for method in self.baselines or default_baselines(self.device):
            for step, seconds, positions in classical_rows(series, method, self.device, self.sirt_iterations):
                s = score_atoms(positions, truth.positions)
                rows.append(
                    self._row(method, step, seconds, s, rss_gb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6)
                )
                print(self._line(rows[-1]), flush=True)
        run_dir = self.output / "run"
        launch = time.time()
        train_ours(
            self.data,
            run_dir,
            self.iterations,
            self.device,
            ("--pipeline.model.snapshot-every", str(self.snapshot_every), *self.extra_args),
            launcher=self.launcher,
        )
        rss_gb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1e6
        snapshots = run_dir / "ours" / "gaussian-atoms" / "run" / "snapshots"
        # the times less what the run's snapshots cost it (the probe's, not the method's)
        times, snapshots_s = read_snapshot_times(snapshots)
        for step, stamp, gaussians, gpu_bytes in times:
            atoms = read_atoms(snapshots / f"step-{int(step):06d}.csv")
            s = score_atoms(atoms.positions, truth.positions)
            rows.append(
                self._row(
                    "ours",
                    int(step),
                    stamp - launch,
                    s,
                    gaussians=int(gaussians),
                    rss_gb=rss_gb,
                    gpu_gb=gpu_bytes / 1e9,
                )
            )
            print(self._line(rows[-1]), flush=True)
        # the result, after the final stage: a run that stops early has no snapshot of it
        written = snapshots.parent / "atoms.xyz"
        if written.is_file():
            atoms = read_atoms(written)
            rows.append(
                self._row(
                    "ours-final",
                    "",
                    written.stat().st_mtime - launch - snapshots_s,
                    score_atoms(atoms.positions, truth.positions),
                    rss_gb=rss_gb,
                    gpu_gb=rows[-1]["peak_gpu_GB"] if times else float("nan"),
                )
            )
            print(self._line(rows[-1]), flush=True)
        self.write(rows)
        return rows

    @staticmethod
    def _row(method, step, seconds, s, gaussians=None, rss_gb=float("nan"), gpu_gb=float("nan")) -> dict:
        return {
            "method": method,
            "step": step,
            "seconds": seconds,
            "tpr": s["tpr"],
            "fp_per_true_atom": s["fp_per_true_atom"],
            "rmsd_pm": s["rmsd_pm"],
            "n_pred": s["n_pred"],
            "gaussians": gaussians if gaussians is not None else s["n_pred"],
            "peak_rss_GB": rss_gb,
            "peak_gpu_GB": gpu_gb,
        }

    @staticmethod
    def _line(r: dict) -> str:
        step = f" step {r['step']}" if r["step"] != "" else ""
        return (
            f"{r['method']}{step}: {r['seconds']:.1f} s TPR {r['tpr']:.4f} FP {r['fp_per_true_atom']:.4f} RMSD "
            f"{r['rmsd_pm']:.1f} pm"
        )

    def write(self, rows: list[dict]) -> None:
        self.output.mkdir(parents=True, exist_ok=True)
        with open(self.output / "time_to_accuracy.csv", "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=FIELDS)
            writer.writeheader()
            writer.writerows(rows)
        lines = [
            "| method | step | time (s) | TPR | FP/atom | RMSD (pm) | atoms | peak RSS (GB) |",
            "| --- | --- | --- | --- | --- | --- | --- | --- |",
        ]
        for r in rows:
            lines.append(
                f"| {r['method']} | {r['step']} | {r['seconds']:.1f} | {r['tpr']:.4f} | {r['fp_per_true_atom']:.4f} | "
                f"{r['rmsd_pm']:.1f} | {r['n_pred']} | {r['peak_rss_GB']:.2f} |"
            )
        (self.output / "time_to_accuracy.md").write_text("\n".join(lines) + "\n")
        plot_time_to_accuracy(rows, self.output / "time_to_accuracy.png")


def default_baselines(device: str) -> tuple[str, ...]:
    """The classical rows a benchmark on ``device`` runs: FBP everywhere; on the CPU
    scikit-image's SART and ASTRA's CPU FBP and SIRT; on a GPU SIRT on the device and ASTRA's
    CUDA FBP and SIRT (ASTRA's rows are skipped, with a line, where it cannot run)."""
    if device == "cpu":
        return ("fbp", "sart", "astra-fbp", "astra-sirt")
    return ("fbp", "sirt", "astra-cuda-fbp", "astra-cuda-sirt")


def classical_rows(series, method: str, device: str = "cpu", sirt_iterations: tuple[int, ...] = SIRT_ITERATIONS):
    """Reconstruct ``series`` with ``method`` (:data:`CLASSICAL`) and trace atoms; yields
    (step, seconds, (M, 3) positions in Å) per result: one for FBP and SART, one per
    ``sirt_iterations`` for SIRT (step: the iterations).  Seconds: from the data in memory
    to traced atoms, the device synchronised.  An ASTRA method that cannot run here yields
    nothing and prints one line saying why."""
    import torch

    from gaussian_atoms_method.harness.astra_rows import astra_slices, astra_unavailable
    from gaussian_atoms_method.harness.tracing import trace_atoms
    from gaussian_atoms_method.physics.reconstruction import reconstruct, sirt, slice_sinograms, slices_to_volume

    if method not in CLASSICAL:
        raise ValueError(f"unknown classical method {method!r}; expected one of {', '.join(CLASSICAL)}")

    def synchronise():
        if torch.cuda.is_available() and device != "cpu":
            torch.cuda.synchronize()

    def traced(volume):
        idx, _ = trace_atoms(volume.data, volume.spacing_A)
        return volume.index_to_A(idx) + series.origin_A

    start = time.perf_counter()
    if method in ("fbp", "sart"):
        volume = reconstruct(
            series.projections,
            series.angles_deg,
            series.pixel_size_A,
            method,
            series.tilt_axis,
            series.centre_px,
            device=device,
            tilt_axis_angle_deg=series.tilt_axis_angle_deg,
        )
        positions = traced(volume)
        yield "", time.perf_counter() - start, positions
        return
    if method.startswith("astra"):
        gpu = method.startswith("astra-cuda")
        reason = astra_unavailable(gpu)
        if reason:
            print(reason, flush=True)
            return
    sino, _, axis_centre = slice_sinograms(
        series.projections, series.tilt_axis, series.centre_px, series.tilt_axis_angle_deg
    )
    if method == "sirt":
        iterates = sirt(sino, series.angles_deg, sirt_iterations, device)
    else:
        iterates = astra_slices(sino, series.angles_deg, method.rsplit("-", 1)[-1], sirt_iterations, gpu)
    tracing = 0.0  # earlier rows' tracing is not part of later rows' time
    for step, slices in iterates:
        synchronise()
        traced_at = time.perf_counter()
        positions = traced(slices_to_volume(slices, series.pixel_size_A, series.tilt_axis, axis_centre))
        now = time.perf_counter()
        yield ("" if method.endswith("fbp") else step), now - start - tracing, positions
        tracing += now - traced_at


def plot_time_to_accuracy(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ours = [r for r in rows if r["method"] == "ours"]
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    for ax, key, label in zip(
        axes, ("tpr", "fp_per_true_atom", "rmsd_pm"), ("TPR", "false positives per atom", "RMSD (pm)")
    ):
        ax.plot([r["seconds"] for r in ours], [r[key] for r in ours], "o-", ms=3, label="ours (during training)")
        final = [r for r in rows if r["method"] == "ours-final"]
        ax.plot(
            [r["seconds"] for r in final], [r[key] for r in final], "*", ms=11, color="C0", label="ours (written atoms)"
        )
        for method, marker in zip(
            dict.fromkeys(r["method"] for r in rows if r["method"] not in ("ours", "ours-final")), "s^vDPX*"
        ):
            points = [r for r in rows if r["method"] == method]
            ax.plot(
                [r["seconds"] for r in points],
                [r[key] for r in points],
                marker + ("--" if len(points) > 1 else ""),
                ms=7,
                label=f"{method} + tracing",
            )
        ax.set_xlabel("wall time (s)")
        ax.set_ylabel(label)
        if key == "fp_per_true_atom":
            ax.set_yscale("symlog", linthresh=1e-3)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
