"""The benchmarks, the stress cases and the sweep: ``baseline``, ``benchmark``,
``benchmark-accuracy``, ``benchmark-peer``, ``benchmark-film``, ``stress``, ``sweep``."""

from __future__ import annotations

import shlex
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional

import tyro

from gaussian_atoms_method.harness.benchmark_options import AccuracyOptions
from gaussian_atoms_method.harness.sweep import SweepOptions


@dataclass
class Baseline:
    """Reconstruct a voxel volume (FBP, SART or an INR), trace atoms in it, write and score them."""

    data: Path
    """Tilt-series directory."""
    output: Path
    """Directory for atoms.xyz, atoms.csv, volume.npy and evaluation.json."""
    method: Literal["fbp", "sart", "inr"] = "sart"
    sart_iterations: int = 1
    inr_steps: int = 10000
    """Training steps of the INR (a batch of rays of one view each)."""
    device: Literal["cpu", "cuda"] = "cpu"
    """Where the INR trains."""
    min_distance_A: float = 2.0
    """Traced atoms are more than this far apart (the paper: 2.0 Å)."""
    threshold_scale: float = 1.0
    """Multiplies the Otsu threshold of the peak intensities."""
    save_volume: bool = False
    """Also write the reconstructed volume (volume.npy)."""

    def main(self) -> None:
        from gaussian_atoms_method.harness.baselines import run_baseline

        run_baseline(
            self.data,
            self.output,
            self.method,
            self.sart_iterations,
            self.inr_steps,
            self.device,
            self.min_distance_A,
            self.threshold_scale,
            self.save_volume,
        )


@dataclass
class BenchmarkAccuracy(AccuracyOptions):
    """The paper's table: simulate (Lobato), reconstruct, trace, evaluate; CSV, Markdown, PNG."""

    quick: bool = False
    """Small particles (scale 0.35, hundreds of atoms) and fewer iterations: minutes on a CPU."""
    scale: Optional[float] = None
    """Particle size relative to the paper's (atom count ~ scale^3); overrides --quick's 0.35.
    Use a separate --output per scale: the data directories are named by particle, tilts and noise."""

    def main(self) -> None:
        from dataclasses import fields

        from gaussian_atoms_method.harness.benchmark import AccuracyBenchmark

        scale = self.scale if self.scale is not None else (0.35 if self.quick else 1.0)
        if not scale > 0:
            raise ValueError(f"--scale must be positive, got {self.scale}")
        options = {f.name: getattr(self, f.name) for f in fields(AccuracyOptions)}
        options["iterations"] = min(self.iterations, 1500) if self.quick else self.iterations
        AccuracyBenchmark(**options, scale=scale).run()
        print(f"wrote {self.output / 'results.md'}, results.csv and accuracy_vs_noise.png")


@dataclass
class BenchmarkPeer:
    """The aSi-208 peer benchmark: reconstruct the peer's three doses, score as the peer did."""

    data: Path = Path("../shared/data/asi208")
    """The peer's folder (Si_Angle.mat, the three dose .mat files, aSi_208atoms_GT.txt)."""
    output: Path = Path("outputs/benchmark-peer")
    doses: tuple[Literal["1.6e5", "1.6e4", "8e3"], ...] = ("1.6e5", "1.6e4", "8e3")
    iterations: int = 3000
    device: Literal["cpu", "cuda"] = "cpu"

    def main(self) -> None:
        from gaussian_atoms_method.harness.peer_benchmark import PeerBenchmark

        # The defaults alone: the model reads the counts' noise and floor from the data.
        PeerBenchmark(self.data, self.output, self.doses, self.iterations, self.device).run()
        print(f"wrote {self.output / 'results.md'} and results.csv")


@dataclass
class BenchmarkFilm:
    """Real data: sub-areas of a measured amorphous Ta film (Yuan et al., Nature Materials 21,
    95-102, 2022), each reconstructed with the defaults and scored against the authors' model."""

    data: Path = Path("../shared/data/ta_film")
    """The film's folder (Projections_area*.mat, angles.mat, alignPara.mat, the model)."""
    output: Path = Path("outputs/benchmark-film")
    areas: tuple[int, ...] = (8, 21, 23, 25)
    iterations: int = 3000
    device: Literal["cpu", "cuda"] = "cpu"
    train_args: str = ""
    """Further ns-train options for each single sub-area's fit (--areas), given with "=", e.g.
    --train-args="--pipeline.model.background plane"; refused with --strips and --simulated."""

    species: str = "Ta"
    """The film's element, written into each sub-area's manifest (it sets the hard core); "" for none."""
    start_from_model: bool = False
    """Start each fit at the authors' model instead of the back-projection's candidates: how much
    of the model the data hold (the fit moves off the rest)."""
    replica: bool = False
    """Fit each sub-area's replica instead: the authors' model (less one of each pair closer than
    tantalum's shortest bond, 2.11 Å) as a known truth in the sub-area's
    own views' geometry, level and noise, through physics the fit does not share (abTEM's Lobato
    potentials with ADF contrast, carbon atoms of a 3 nm support, a 300 kV probe's rings and tails,
    a 0.7 Å source and a 6% halo), 0.5 px of per-view misregistration and 6.8% gain scatter; each
    fitted with its strip neighbours' replicas as a film, whose overlap decides the per-view
    registration (`gaussian-atoms film`'s default; --no-registration-by-overlap: each alone, once)."""
    strips: tuple[int, ...] = ()
    """Instead of single sub-areas: these published strips (1: areas 1-16, 2: areas 17-29), each
    fitted on Ray (`gaussian-atoms film`), joined and scored in the strip's interior."""
    tasks_per_gpu: int = 1
    """With --strips or --replica on GPUs: sub-areas fitted at once on each GPU."""
    registration_by_overlap: bool = True
    """With --strips, --simulated or --replica: per-view shifts and gains decided by the overlapping
    sub-areas, every sub-area fitted without and with them (`gaussian-atoms film`'s default)."""

    simulated: bool = False
    """Instead: the harness's film (Lobato, wider than each tile) cut into tiles, fitted on Ray,
    joined and scored against its truth, the seams included."""

    def main(self) -> None:
        if (self.strips or self.simulated) and self.train_args:
            raise ValueError(
                "--train-args reaches the fits of single sub-areas (--areas) only; --strips and --simulated fit "
                "with the defaults (--iterations and --species apply to --strips)"
            )
        if self.simulated:
            import json

            from gaussian_atoms_method.harness.film_strip import simulated_film

            film = simulated_film(
                self.output / "simulated", device=self.device, registration_by_overlap=self.registration_by_overlap
            )
            print("simulated film: " + json.dumps(film))
            return
        if self.strips:
            import json

            from gaussian_atoms_method.harness.film_strip import run_strip

            for strip in self.strips:
                print(
                    f"Ta film strip {strip}: "
                    + json.dumps(
                        run_strip(
                            strip,
                            self.data,
                            self.output,
                            self.device,
                            tasks_per_gpu=self.tasks_per_gpu,
                            registration_by_overlap=self.registration_by_overlap,
                            species=self.species or None,
                            max_steps=self.iterations,
                        )
                    )
                )
            return
        from gaussian_atoms_method.harness.film_benchmark import FilmBenchmark

        bench = FilmBenchmark(
            self.data,
            self.output,
            self.areas,
            self.iterations,
            self.device,
            tuple(shlex.split(self.train_args)),
            self.species,
            self.start_from_model,
            self.replica,
        )
        if self.replica and self.registration_by_overlap:
            from gaussian_atoms_method.harness.film_replica import replica_film

            replica_film(bench, self.tasks_per_gpu)
        else:
            bench.run()
        print(f"wrote {self.output / 'results.md'} and results.csv")


@dataclass
class Benchmark:
    """Time to accuracy: our method scored during training against FBP and SART + tracing on
    the same data; CSV, Markdown and a PNG of error against wall time."""

    data: Path
    """A tilt-series directory with a truth file (e.g. from simulate or benchmark-accuracy)."""
    output: Path = Path("outputs/benchmark")
    iterations: int = 3000
    snapshot_every: int = 100
    """Score our atoms every this many training steps."""
    device: Literal["cpu", "cuda"] = "cpu"
    baselines: tuple[
        Literal["fbp", "sart", "sirt", "astra-fbp", "astra-sirt", "astra-cuda-fbp", "astra-cuda-sirt"], ...
    ] = ()
    """Classical reconstructions + tracing in the same run; none given: FBP, scikit-image's SART
    and ASTRA's CPU FBP and SIRT on the CPU, FBP, SIRT on the GPU and ASTRA's CUDA FBP and SIRT on
    cuda (ASTRA's rows are skipped, with a line, without astra-toolbox or its CUDA libraries)."""
    train_args: str = ""
    """Further ns-train options for our run, given with "=", e.g. --train-args="--pipeline.model.coarse-steps 500"."""
    launcher: Literal["gaussian-atoms", "ns-train"] = "gaussian-atoms"
    """Start our run with `gaussian-atoms train` or `ns-train gaussian-atoms` (same training,
    longer start-up): the time since launch includes it."""
    sirt_iterations: tuple[int, ...] = (10, 25, 50, 100, 200)
    """SIRT rows (ours and ASTRA's): trace after this many iterations (increasing)."""

    def main(self) -> None:
        from gaussian_atoms_method.harness.time_to_accuracy import TimeToAccuracy

        if self.snapshot_every <= 0:
            raise ValueError(f"--snapshot-every must be positive, got {self.snapshot_every}")
        if not self.sirt_iterations or any(b <= a for a, b in zip((0,) + self.sirt_iterations, self.sirt_iterations)):
            raise ValueError(
                f"--sirt-iterations must be positive and increasing, got {' '.join(map(str, self.sirt_iterations))}"
            )
        TimeToAccuracy(
            self.data,
            self.output,
            self.iterations,
            self.snapshot_every,
            self.device,
            self.baselines,
            tuple(shlex.split(self.train_args)),
            self.launcher,
            self.sirt_iterations,
        ).run()
        print(f"wrote {self.output / 'time_to_accuracy.md'}, .csv and .png")


@dataclass
class Stress:
    """Numerical stress cases: float32 vs float64 projections and gradients (sigma 0.05-20 px,
    amplitudes 1e-3-1e3), atoms on and beyond the edge, coincident atoms, all-zero projections,
    SNR below 1, 100k atoms.  Exit status 1 if any case fails."""

    quick: bool = False
    """Leave out the slow cases (training at SNR < 1, 100k atoms)."""

    def main(self) -> None:
        from gaussian_atoms_method.harness.stress import run_stress

        cases = run_stress(include_slow=not self.quick)
        print("| case | result | detail |\n| --- | --- | --- |")
        for name, ok, detail in cases:
            print(f"| {name} | {'pass' if ok else 'FAIL'} | {detail} |")
        failed = [name for name, ok, _ in cases if not ok]
        if failed:
            print(f"gaussian-atoms stress: {len(failed)} case(s) failed: {', '.join(failed)}", file=sys.stderr)
            raise SystemExit(1)


@dataclass
class Sweep(SweepOptions):
    """Run ns-train gaussian-atoms over a grid of tyro overrides and tabulate settings against
    metrics and wall time (sweep.csv, sweep.md).  The grid follows ``--``: each ns-train option
    with its values; every combination is one run.  Finished runs are skipped, so an
    interrupted sweep resumes.  Example: ``gaussian-atoms sweep --data data/sim --jobs 2 --
    --pipeline.model.merge-threshold-A 0.2 0.3 0.5 --pipeline.model.merge-every 50 100``."""

    grid: tyro.conf.Suppress[tuple[str, ...]] = ()
    """Read from the tokens after ``--`` (:func:`split_grid`), not as an option."""

    def main(self) -> None:
        from dataclasses import fields

        from gaussian_atoms_method.harness.sweep import Sweep as SweepRunner

        rows = SweepRunner(**{f.name: getattr(self, f.name) for f in fields(SweepOptions)}).run()
        failed = [r for r in rows if r.get("status") != "ok"]
        if failed:
            print(f"gaussian-atoms sweep: {len(failed)} of {len(rows)} runs failed (see sweep.md)", file=sys.stderr)
            raise SystemExit(1)


def split_grid(tokens: list[str]) -> tuple[str, ...]:
    """``--a 1 2 --b 3`` -> ``("--a 1 2", "--b 3")`` (checked by :func:`.sweep.parse_grid`)."""
    entries: list[list[str]] = []
    for token in tokens:
        if token.startswith("--") or not entries:
            entries.append([token])
        else:
            entries[-1].append(token)
    return tuple(" ".join(shlex.quote(t) for t in entry) for entry in entries)
