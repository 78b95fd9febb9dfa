"""``gaussian-atoms <verb>``: one tyro CLI whose verbs call the physics core.

Verbs: ``simulate`` (write a tilt-series directory with known atoms), ``evaluate`` (score
predicted atoms against the truth), ``baseline`` (FBP/SART + atom tracing), the benchmarks,
``stress``, ``export`` and ``sweep``.  Training is ``ns-train gaussian-atoms`` or, with
the same options and a shorter start-up, ``gaussian-atoms train``.
"""

from __future__ import annotations

import json
import shlex
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal, Optional, Union

import tyro


@dataclass
class Simulate:
    """Simulate a tilt series with known atoms and write a tilt_series.json directory."""

    output: Path = Path("data/sim")
    """Directory to write (tilt_series.json, projections.npy, angles.txt, atoms_true.xyz)."""
    particle: str = "au"
    """au, fept, apd, hea, carbon, asi, film (amorphous Pd, 110 x 40 x 20 Å: give --field-of-view-A),
    sphere (an fcc sphere of --element, --radius-A) or a structure file."""
    scale: Optional[float] = None
    """Linear size factor (atom count ~ scale^3) of the named particles (default 1): the generated ones grow or shrink,
    au and structure files are cut (at most 1)."""
    element: Optional[str] = None
    """Element of the fcc sphere (--particle sphere; default Au)."""
    radius_A: Optional[float] = None
    """Radius of the fcc sphere, Å (--particle sphere; default 10)."""
    potential: Literal["lobato", "gaussian"] = "lobato"
    """abTEM Lobato projected potential (independent physics), or the quick Gaussian model."""
    tilts: str = "limited"
    """Tilt scheme: full (-90:1:90), limited (-70:3:68), sampled, wedge, 'start:step:stop' or a comma list (deg)."""
    pixel_size_A: float = 0.25
    atom_sigma_A: float = 0.35
    """Width of each atom of the Gaussian potential, Å (--potential gaussian)."""
    blur_sigma_A: float = 0.5
    """Gaussian probe blur, Å."""
    probe: Literal["gaussian", "aberrated"] = "gaussian"
    """The blur: a Gaussian of --blur-sigma-A, or an aberrated STEM probe's intensity (20 mrad,
    300 kV, 40 Å defocus, 10 µm Cs: rings and tails)."""
    floor_fraction: float = 0.0
    """A floor under every view, as a fraction of a column's value (0: none)."""
    floor_variation: float = 0.0
    """How much the floor varies across a view (a random ramp), as a fraction of the floor."""
    noise_std: float = 50.0
    """Standard deviation of the additive Gaussian noise, projection units (V·Å for Lobato)."""
    field_of_view_A: Optional[float] = None
    """Side of the detector, Å, when it sees less than the object (a film): the views are
    projected through all of it and cropped; the truth holds the atoms above the detector.
    Default: the detector spans the object."""
    tilt_axis: Literal["x", "y"] = "y"
    seed: int = 0
    save_volume: bool = True
    """Also write the true potential volume, blurred like the data (for the SSIM metric)."""

    @property
    def particle_scale(self) -> float | None:
        """The size factor of a named particle (1 unless given); None for the sphere."""
        return None if self.particle == "sphere" else (1.0 if self.scale is None else self.scale)

    def main(self) -> None:
        import numpy as np

        from dataparsers.tilt_series_format import update_manifest, write_tilt_series
        from gaussian_atoms_method.harness.particles import make_particle
        from gaussian_atoms_method.harness.simulate import (
            parse_tilts,
            simulate_tilt_series,
            spherical_particle,
            true_potential_volume,
        )

        # Options that would be ignored are refused: `--element Au --radius-A 11` without
        # `--particle sphere` once simulated the 6,679-atom Au particle instead.
        if self.particle == "sphere":
            if self.scale is not None:
                raise ValueError("--scale applies to the named particles; give --radius-A for --particle sphere")
            particle = spherical_particle(self.element or "Au", 10.0 if self.radius_A is None else self.radius_A)
        else:
            ignored = [
                name
                for name, value in (("--element", self.element), ("--radius-A", self.radius_A))
                if value is not None
            ]
            if ignored:
                raise ValueError(f"{' and '.join(ignored)} apply to --particle sphere, not --particle {self.particle}")
            particle = make_particle(self.particle, self.particle_scale, self.seed)
        # The tilt centre is the particle's centroid; the truth keeps the particle's own frame.
        origin = particle.positions.mean(axis=0)
        sim = simulate_tilt_series(
            particle.shifted(-origin),
            parse_tilts(self.tilts),
            potential=self.potential,
            pixel_size_A=self.pixel_size_A,
            atom_sigma_A=self.atom_sigma_A,
            blur_sigma_A=self.blur_sigma_A,
            noise_std=self.noise_std,
            tilt_axis=self.tilt_axis,
            seed=self.seed,
            probe=self.probe,
            floor_fraction=self.floor_fraction,
            floor_variation=self.floor_variation,
            field_of_view_A=self.field_of_view_A,
        )
        truth = sim.truth.shifted(origin)
        write_tilt_series(
            self.output,
            sim.projections,
            sim.angles_deg,
            sim.pixel_size_A,
            truth=truth,
            origin_A=origin,
            tilt_axis=self.tilt_axis,
            extra={
                "simulation": {
                    "particle": self.particle,
                    "scale": self.particle_scale,
                    "potential": self.potential,
                    "noise_std": self.noise_std,
                    "peak_to_noise": sim.peak_to_noise,
                    "blur_sigma_A": self.blur_sigma_A,
                    "probe": self.probe,
                    "floor_fraction": self.floor_fraction,
                    "floor_variation": self.floor_variation,
                    "field_of_view_A": self.field_of_view_A,
                    "seed": self.seed,
                }
            },
        )
        n, h, w = sim.projections.shape
        if self.save_volume:
            volume = true_potential_volume(
                sim.truth, self.potential, self.pixel_size_A, h, self.atom_sigma_A, self.blur_sigma_A
            )
            np.save(self.output / "potential_volume.npy", volume)
            update_manifest(self.output, volume="potential_volume.npy", volume_voxel_size_A=self.pixel_size_A)
        print(
            f"wrote {self.output}: {len(truth)} atoms, {n} tilts "
            f"({np.min(sim.angles_deg):g}..{np.max(sim.angles_deg):g} deg), "
            f"{h}x{w} px at {self.pixel_size_A} Å, {self.potential} potential, noise {self.noise_std:g}, peak-to-noise "
            f"{sim.peak_to_noise:.1f}"
        )


@dataclass
class Evaluate:
    """Score predicted atoms against the truth (JSON to stdout, summary to stderr)."""

    pred: Path
    """Predicted atoms (xyz/extxyz/csv or any ASE format)."""
    truth: Optional[Path] = None
    """True atoms; or give --data."""
    data: Optional[Path] = None
    """A tilt-series directory: its truth file, and its potential volume for SSIM."""
    radius_A: float = 0.75
    """A true atom is found if a predicted atom lies within this distance (Å)."""
    mean_shift: bool = False
    """Align first by an iterated global mean shift (the Miao group's scoring)."""
    interior_A: Optional[float] = None
    """Score only the true and predicted atoms at least this far inside the detector's footprint
    (an object wider than the field of view; needs --data)."""
    output: Optional[Path] = None
    """Also write the JSON here."""

    def main(self) -> None:
        from gaussian_atoms_method.atoms.atom_set import read_atoms
        from gaussian_atoms_method.harness.evaluation import (
            evaluate_atoms,
            inside_footprint,
            load_reference,
            summary_line,
        )

        if (self.truth is None) == (self.data is None):
            raise ValueError("give exactly one of --truth and --data")
        if self.interior_A is not None and self.data is None:
            raise ValueError("--interior-A needs --data (the detector's footprint)")
        pred = read_atoms(self.pred)
        volume = voxel = None
        origin = (0.0, 0.0, 0.0)
        if self.data is not None:
            series, truth, volume, voxel = load_reference(self.data)
            origin = series.origin_A
            if self.interior_A is not None:
                pred, truth = (a.subset(inside_footprint(a.positions, series, self.interior_A)) for a in (pred, truth))
                volume = None  # the volume spans the whole cube
        else:
            truth = read_atoms(self.truth)
        if volume is not None and (pred.sigmas is None or pred.amplitudes is None):
            volume = None  # atoms without widths (a traced baseline): no volume to compare
        scores = evaluate_atoms(pred, truth, self.radius_A, self.mean_shift, volume, voxel, origin)
        text = json.dumps(scores, indent=2)
        if self.output is not None:
            self.output.write_text(text + "\n")
        print(text)
        print(summary_line(scores, str(self.pred)), file=sys.stderr)


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
class BenchmarkAccuracy:
    """The paper's table: simulate (Lobato), reconstruct, trace, evaluate; CSV, Markdown, PNG."""

    output: Path = Path("outputs/benchmark-accuracy")
    particles: tuple[str, ...] = ("au",)
    tilts: tuple[str, ...] = ("full", "limited")
    noise: tuple[float, ...] = (50.0, 200.0, 500.0)
    methods: tuple[str, ...] = ("fbp", "sart", "ours")
    quick: bool = False
    """Small particles (scale 0.35, hundreds of atoms) and fewer iterations: minutes on a CPU."""
    scale: Optional[float] = None
    """Particle size relative to the paper's (atom count ~ scale^3); overrides --quick's 0.35.
    Use a separate --output per scale: the data directories are named by particle, tilts and noise."""
    iterations: int = 3000
    """Training iterations of our method."""
    device: Literal["cpu", "cuda"] = "cpu"
    pixel_size_A: float = 0.25
    """Detector pixel size of the simulated projections, Å."""
    noise_kind: Literal["gaussian", "poisson"] = "gaussian"
    """``gaussian``: --noise is the standard deviation of additive noise; ``poisson``: --noise is
    the dose as expected counts at the brightest pixel (Poisson counts on a one-count floor)."""

    def main(self) -> None:
        from gaussian_atoms_method.harness.benchmark import AccuracyBenchmark

        scale = self.scale if self.scale is not None else (0.35 if self.quick else 1.0)
        if not scale > 0:
            raise ValueError(f"--scale must be positive, got {self.scale}")
        bench = AccuracyBenchmark(
            output=self.output,
            particles=self.particles,
            tilts=self.tilts,
            noise=self.noise,
            methods=self.methods,
            scale=scale,
            iterations=min(self.iterations, 1500) if self.quick else self.iterations,
            device=self.device,
            pixel_size_A=self.pixel_size_A,
            noise_kind=self.noise_kind,
        )
        bench.run()
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
    """Further ns-train options, given with "=", e.g. --train-args="--pipeline.model.background plane"."""

    species: str = "Ta"
    """The film's element, written into each sub-area's manifest (it sets the hard core); "" for none."""
    start_from_model: bool = False
    """Start each fit at the authors' model instead of the back-projection's candidates: how much
    of the model the data hold (the fit moves off the rest)."""

    def main(self) -> None:
        from gaussian_atoms_method.harness.film_benchmark import FilmBenchmark

        FilmBenchmark(
            self.data,
            self.output,
            self.areas,
            self.iterations,
            self.device,
            tuple(shlex.split(self.train_args)),
            self.species,
            self.start_from_model,
        ).run()
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
class View:
    """Open a finished run in nerfstudio's viewer (the atoms as points coloured by mass over the
    projections), served to this machine only unless --host says otherwise."""

    load_config: Path
    """The run's config.yml."""
    host: str = "127.0.0.1"
    """The address the viewer listens on: 127.0.0.1 is this machine only; 0.0.0.0 every network."""
    port: Optional[int] = None
    """The viewer's port (default nerfstudio's, 7007, or the next free one)."""

    def build(self):
        """nerfstudio's ``ns-viewer`` command with these settings, built but not run."""
        from gaussian_atoms_method.nerfstudio_layer.viewer import viewer_command

        if not self.load_config.is_file():
            raise FileNotFoundError(f"{self.load_config}: run config not found")
        return viewer_command(self.load_config, self.host, self.port)

    def main(self) -> None:
        self.build().main()


@dataclass
class HeldOutViews:
    """Choose the point-spread function by the views a fit did not see: for each candidate
    kernel, fit the even views and predict the odd ones, then the other way round; the kernel
    whose fits predict the unseen views best is the one the data support (held_out.md)."""

    data: Path
    """A tilt-series directory (tilt_series.json)."""
    output: Path = Path("outputs/held-out")
    kernels: tuple[str, ...] = ("learned", "0,0.1,0.1", "0,0.15,0.2", "0,0.2,0.3")
    """``learned`` (the default run) or three intensity fractions ``a,b,c`` at 1, 2 and 4 Å, held."""
    device: Literal["cpu", "cuda"] = "cpu"
    iterations: int = 3000
    interior_px: tuple[int, int] = (0, 0)
    """Rows and columns left out at each detector edge when scoring."""
    train_args: str = ""
    """Further ns-train options, given with "=", e.g. --train-args="--pipeline.model.background plane"."""

    def main(self) -> None:
        from gaussian_atoms_method.harness.kernel_choice import compare_kernels

        compare_kernels(self.data, self.output, self.kernels, self.device, self.iterations, self.interior_px,
                        tuple(shlex.split(self.train_args)))  # fmt: skip


@dataclass
class CheckPrecision:
    """Each atom's stated position precision against its actual error, on finished runs whose
    data have a truth file: per axis, the median stated standard deviation, the actual RMS error
    and the share within one and two of them (0.683 and 0.954 if the statement were exact)."""

    load_config: tuple[Path, ...]
    """The runs' config.yml files."""
    output: Optional[Path] = None
    """Also write the tables here (markdown)."""

    def main(self) -> None:
        from gaussian_atoms_method.harness.precision_check import check_precision, precision_table

        for config in self.load_config:
            if not config.is_file():
                raise FileNotFoundError(f"{config}: run config not found")
        table = precision_table([check_precision(c) for c in self.load_config])
        print(table)
        if self.output is not None:
            self.output.write_text(table)


@dataclass
class InputMatrix:
    """Run every broken and odd tilt series of the catalogue through the front door and print a
    table: a broken one passes with one line of its own, a non-zero exit, no traceback and no
    run directory left; an odd one passes when it trains.  Exit status 1 if any fails."""

    launcher: Literal["ns-train", "gaussian-atoms"] = "ns-train"
    output: Path = Path("outputs/input-matrix")

    def main(self) -> None:
        from gaussian_atoms_method.harness.input_matrix import run_matrix

        rows = run_matrix(self.launcher, self.output)
        failed = [r["case"] for r in rows if not r["passed"]]
        print(f"{len(rows) - len(failed)} passed, {len(failed)} failed" + (f": {failed}" if failed else ""))
        if failed:
            raise SystemExit(1)


@dataclass
class Screenshot:
    """A PNG of nerfstudio's viewer showing a finished run's atoms, taken in headless Chromium
    (Selenium; WebGL through SwiftShader, no GPU).  Exit status 1 unless the atoms show.  Needs
    ``apt-get install chromium chromium-driver`` and ``pip install selenium``."""

    load_config: Path
    """The run's config.yml."""
    output: Path = Path("viewer.png")
    wait_s: float = 25.0
    """Seconds the page is given to connect and draw the scene."""

    def main(self) -> None:
        from gaussian_atoms_method.harness.viewer_screenshot import screenshot

        if not self.load_config.is_file():
            raise FileNotFoundError(f"{self.load_config}: run config not found")
        try:
            fraction = screenshot(self.load_config, self.output, self.wait_s)
        except (RuntimeError, TimeoutError, ImportError) as exc:
            raise ValueError(str(exc)) from None
        print(f"wrote {self.output}: {fraction:.4f} of the pixels are atom-coloured")
        if fraction < 1e-3:
            print("gaussian-atoms screenshot: the atoms are not visible in the screenshot", file=sys.stderr)
            raise SystemExit(1)


@dataclass
class Export:
    """Write a finished run's atoms as .xyz/.extxyz (with sigma_A, amplitude), .csv or .cif,
    optionally with species assigned by clustering the atoms' integrated masses."""

    load_config: Path
    """The run's config.yml (its directory holds the atoms.xyz written at the end of training)."""
    output: Path
    species: Optional[str] = None
    """Comma-separated elements, e.g. Fe,Pt: heavier element = larger integrated mass."""

    def main(self) -> None:
        from gaussian_atoms_method.atoms.atom_set import read_atoms, write_atoms
        from gaussian_atoms_method.atoms.species import classify_species

        if not self.load_config.is_file():
            raise FileNotFoundError(f"{self.load_config}: run config not found")
        source = self.load_config.parent / "atoms.xyz"
        if not source.is_file():
            raise FileNotFoundError(f"{source}: not found; the run writes it when training finishes")
        atoms = read_atoms(source)
        if self.species:
            if atoms.masses is None:
                raise ValueError(f"{source}: has no sigma_A/amplitude columns to classify species by")
            atoms.species, report = classify_species(
                atoms.masses, [e.strip() for e in self.species.split(",") if e.strip()]
            )
            print(json.dumps({"species": report}))
            if not report.get("separated", True):
                print(
                    f"gaussian-atoms: the atoms' masses show {report['populations']} separate population(s), not one "
                    f"per element ({report['test']}): every atom written as {atoms.species[0]}",
                    file=sys.stderr,
                )
        write_atoms(atoms, self.output)
        print(f"wrote {len(atoms)} atoms to {self.output}")


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
class Sweep:
    """Run ns-train gaussian-atoms over a grid of tyro overrides and tabulate settings against
    metrics and wall time (sweep.csv, sweep.md).  The grid follows ``--``: each ns-train option
    with its values; every combination is one run.  Finished runs are skipped, so an
    interrupted sweep resumes.  Example: ``gaussian-atoms sweep --data data/sim --jobs 2 --
    --pipeline.model.merge-threshold-A 0.2 0.3 0.5 --pipeline.model.merge-every 50 100``."""

    data: Path
    """Tilt-series directory (with a truth file the runs are scored)."""
    output: Path = Path("outputs/sweep")
    iterations: int = 3000
    jobs: int = 1
    """Runs at a time (local backend); the machine's threads are shared between them."""
    device: Literal["cpu", "cuda"] = "cpu"
    backend: Literal["local", "ray"] = "local"
    """local processes, or a Ray cluster (pip install 'gaussian-atoms[ray]')."""
    ray_address: Optional[str] = None
    """Address of an existing Ray cluster (default: start a local one)."""
    grid: tyro.conf.Suppress[tuple[str, ...]] = ()

    def main(self) -> None:
        from gaussian_atoms_method.harness.sweep import Sweep as SweepRunner

        rows = SweepRunner(
            self.data,
            self.output,
            self.grid,
            (),
            self.iterations,
            self.jobs,
            self.device,
            self.backend,
            self.ray_address,
        ).run()
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


@dataclass
class Train:
    """Train on a tilt series with the options of ns-train gaussian-atoms, started sooner
    (gaussian-atoms train -h lists them)."""

    def main(self) -> None:  # the entry point hands "train ..." to train.run before tyro
        raise AssertionError("unreachable")


Commands = Union[
    Annotated[Train, tyro.conf.subcommand("train")],
    Annotated[Simulate, tyro.conf.subcommand("simulate")],
    Annotated[Evaluate, tyro.conf.subcommand("evaluate")],
    Annotated[Baseline, tyro.conf.subcommand("baseline")],
    Annotated[Benchmark, tyro.conf.subcommand("benchmark")],
    Annotated[BenchmarkAccuracy, tyro.conf.subcommand("benchmark-accuracy")],
    Annotated[BenchmarkPeer, tyro.conf.subcommand("benchmark-peer")],
    Annotated[BenchmarkFilm, tyro.conf.subcommand("benchmark-film")],
    Annotated[Stress, tyro.conf.subcommand("stress")],
    Annotated[Export, tyro.conf.subcommand("export")],
    Annotated[View, tyro.conf.subcommand("view")],
    Annotated[Sweep, tyro.conf.subcommand("sweep")],
    Annotated[HeldOutViews, tyro.conf.subcommand("held-out-views")],
    Annotated[CheckPrecision, tyro.conf.subcommand("check-precision")],
    Annotated[InputMatrix, tyro.conf.subcommand("input-matrix")],
    Annotated[Screenshot, tyro.conf.subcommand("screenshot")],
]


def parse(argv: list[str]) -> object:
    """What ``gaussian-atoms ARGV`` would run, built but not run: for ``train`` its nerfstudio
    TrainerConfig (the options of ``ns-train gaussian-atoms``), otherwise the verb's dataclass
    (a sweep with its grid, ns-train's own options passed through after "--")."""
    if argv[:1] == ["train"]:
        from gaussian_atoms_method.nerfstudio_layer.launch import build_config

        return build_config(argv[1:])
    grid: tuple[str, ...] = ()
    if argv[:1] == ["sweep"] and "--" in argv:
        cut = argv.index("--")
        argv, grid = argv[:cut], split_grid(argv[cut + 1 :])
    command = tyro.cli(Commands, args=argv)
    if isinstance(command, Sweep):
        command.grid = grid
    return command


def entrypoint(argv: list[str] | None = None) -> None:
    """Run one verb; errors in the user's input are reported in one line, exit status 2."""
    from dataparsers.tilt_series_format import TiltSeriesError
    from gaussian_atoms_method.atoms.atom_set import AtomFileError

    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["train"]:
        from gaussian_atoms_method.start_ahead import begin_for, end_now

        begin_for(argv[1:])  # the start computed in a thread while nerfstudio loads
        from gaussian_atoms_method.nerfstudio_layer.config import INPUT_ERRORS
        from gaussian_atoms_method.nerfstudio_layer.launch import exit_process
        from gaussian_atoms_method.nerfstudio_layer.launch import run as train_run

        try:
            config = parse(argv)
        except SystemExit as exc:  # the command line's own errors (and --help), said by tyro
            end_now(exc.code if isinstance(exc.code, int) else 2)
            raise
        try:
            train_run(config)
        except INPUT_ERRORS as exc:
            print(f"gaussian-atoms train: error: {exc}", file=sys.stderr)
            end_now(2)
            raise SystemExit(2) from None
        exit_process(0)  # the run's files are complete: no teardown of what it loaded
    command = parse(argv)
    try:
        command.main()
    except (TiltSeriesError, AtomFileError, ValueError, FileNotFoundError) as exc:
        print(f"gaussian-atoms: error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None


if __name__ == "__main__":
    entrypoint()
