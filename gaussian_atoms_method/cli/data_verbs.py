"""The verbs on a user's data: ``simulate``, ``train``, ``evaluate``, ``export`` and ``view``."""

from __future__ import annotations

import dataclasses
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional


@dataclass
class Simulate:
    """Simulate a tilt series with known atoms and write a tilt_series.json directory."""

    output: Path = Path("data/sim")
    """Directory to write (tilt_series.json, projections.npy, angles.txt, atoms_true.xyz)."""
    particle: str = "au"
    """au, fept, apd, apd-close (amorphous Pd with a measured glass's close pairs), hea, carbon, asi,
    film (amorphous Pd, 110 x 40 x 20 Å: give --field-of-view-A), sphere (an fcc sphere of --element,
    --radius-A) or a structure file."""
    scale: Optional[float] = None
    """Linear size factor (atom count ~ scale^3) of the named particles (default 1): the generated ones grow or shrink,
    au and structure files are cut (at most 1)."""
    element: Optional[str] = None
    """Element of the fcc sphere (--particle sphere; default Au)."""
    radius_A: Optional[float] = None
    """Radius of the fcc sphere, Å (--particle sphere; default 10)."""
    potential: Literal["lobato", "adf", "phase", "gaussian"] = "lobato"
    """abTEM Lobato projected potential (independent physics); adf: each atom a power of its Lobato
    projected potential with ADF-STEM's Z^1.7 contrast, the probe drawn with it (independent physics
    too); phase: ptychographic phase images in rad (each atom its projected potential through the
    aperture's double overlap and the source, --voltage-kV --semiangle-mrad --source-fwhm-A; the
    noise of --dose-e-per-A2); or the quick Gaussian model (the fit's own: for demos and unit tests, not evidence). With
    --like, lobato and adf both draw ADF atoms, gaussian a Gaussian of --atom-sigma-A."""
    tilts: str = "limited"
    """Tilt scheme: full (-90:1:90), limited (-70:3:68), sampled, wedge, 'start:step:stop' or a comma list (deg)."""
    pixel_size_A: float = 0.25
    atom_sigma_A: Optional[float] = None
    """Width of each atom of the Gaussian potential, Å (--potential gaussian; default 0.35, 0.4 with --like)."""
    blur_sigma_A: float = 0.5
    """Gaussian probe blur, Å."""
    probe: Optional[Literal["gaussian", "aberrated"]] = None
    """The blur: a Gaussian of --blur-sigma-A, or a STEM probe's intensity from its optics
    (--voltage-kV, --semiangle-mrad, --defocus-A, --cs-A, --source-fwhm-A, --halo-fraction: rings,
    tails, the source's spread). Default: aberrated with --like, gaussian for the named particles."""
    voltage_kV: float = 300.0
    """The aberrated probe's accelerating voltage, kV."""
    semiangle_mrad: float = 20.0
    """The aberrated probe's convergence semi-angle, mrad."""
    defocus_A: float = 40.0
    """The aberrated probe's defocus, Å."""
    cs_A: float = 1e5
    """The aberrated probe's spherical aberration, Å (1e5: 10 µm)."""
    source_fwhm_A: Optional[float] = None
    """The aberrated probe's effective source, a Gaussian of this FWHM, Å. Default: 0.7 with --like
    (an aberration-corrected field-emission STEM's 0.5-1 Å), 0 for the named particles."""
    halo_fraction: float = 0.0
    """The share of the aberrated probe's intensity in a Lorentzian halo (half width --halo-hwhm-A)."""
    halo_hwhm_A: float = 2.0
    """The halo's half width at half maximum, Å."""
    scan_jitter_px: float = 0.0
    """With --like: each scan line (row) of each view shifted along the fast axis by this RMS, pixels."""
    crop_order: int = 0
    """With --like: each noisy view cropped about a random sub-pixel centre with splines of this
    order (3: cubic, as measured views are often cropped and aligned; 0: not), so its noise is
    correlated as theirs is; the atoms stay registered."""
    noise_over_atom: float = 1.0
    """With --like: the views' noise over an atom in units of what neighbouring pixels show, as a
    run on the real views prints it (read from what neighbouring views do not share); above 1 the
    replica's noise is drawn correlated with both readings (give --noise-sigma-A too); 1: white."""
    noise_sigma_A: float = 0.0
    """With --noise-over-atom: the atoms' width it was read at, Å (the run prints it beside it)."""
    floor_fraction: float = 0.0
    """A floor under every view, as a fraction of a column's value (0: none)."""
    floor_variation: float = 0.0
    """How much the floor varies across a view (a random ramp), as a fraction of the floor."""
    noise_std: float = 50.0
    """Standard deviation of the additive Gaussian noise, projection units (V·Å for Lobato)."""
    dose_e_per_A2: Optional[float] = None
    """With --potential phase: the electrons per Å² of each view, whose phase noise the views get
    (1 / sqrt(2 N) rad for N electrons on a pixel, spread over the aperture's band) instead of
    --noise-std."""
    field_of_view_A: Optional[float] = None
    """Side of the detector, Å, when it sees less than the object (a film): the views are
    projected through all of it and cropped; the truth holds the atoms above the detector.
    Default: the detector spans the object."""
    tilt_axis: Literal["x", "y"] = "y"
    seed: int = 0
    save_volume: bool = True
    """Also write the true potential volume, blurred like the data (for the SSIM metric)."""
    like: Optional[Path] = None
    """A real tilt series (a directory with tilt_series.json, or a file) to replicate: its
    orientations, detector, pixel size, tilt centre, mean level and noise; the atoms are
    --particle's structure file (in its frame about the tilt centre) or, by default, its truth
    file. --tilts, --pixel-size-A, --noise-std and --field-of-view-A are then not used."""
    support_A: float = 0.0
    """With --like: an amorphous carbon support film this thick under the atoms, Å (0: none)."""
    shift_px: float = 0.0
    """With --like: each view shifted at random by this RMS along each detector axis, pixels."""
    shifts_from: Optional[Path] = None
    """With --like: each view shifted as this registration.csv says (what a fit of the real
    views learned, --pipeline.model.refine-alignment) instead of at random: the experiment's own
    misregistration."""
    gain_scatter: float = 0.0
    """With --like: each view's gain scattered by this relative RMS."""
    keep_close_pairs: bool = False
    """With --like: keep atoms closer than the shortest bond their elements can form in the truth.
    By default one of each such pair (a measured model's error; no specimen holds it) is set aside
    and the run says how many."""

    def optics(self):
        """The aberrated probe's :class:`~gaussian_atoms_method.physics.microscope.ProbeOptics`."""
        from gaussian_atoms_method.physics.microscope import ProbeOptics

        source = self.source_fwhm_A if self.source_fwhm_A is not None else (0.7 if self.like is not None else 0.0)
        optics = (self.voltage_kV, self.semiangle_mrad, self.defocus_A, self.cs_A)
        return ProbeOptics(*optics, source, self.halo_fraction, self.halo_hwhm_A)

    @property
    def particle_atom_sigma_A(self) -> float:
        """The Gaussian atom's width: as given, else 0.35 Å for particles and 0.4 Å with --like."""
        return self.atom_sigma_A if self.atom_sigma_A is not None else (0.4 if self.like is not None else 0.35)

    @property
    def particle_scale(self) -> float | None:
        """The size factor of a named particle (1 unless given); None for the sphere."""
        return None if self.particle == "sphere" else (1.0 if self.scale is None else self.scale)

    def main(self) -> None:
        if self.like is not None:
            return self.replicate()
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
            atom_sigma_A=self.particle_atom_sigma_A,
            blur_sigma_A=self.blur_sigma_A,
            noise_std=self.noise_std,
            tilt_axis=self.tilt_axis,
            seed=self.seed,
            probe=self.probe or "gaussian",
            optics=self.optics(),
            floor_fraction=self.floor_fraction,
            floor_variation=self.floor_variation,
            field_of_view_A=self.field_of_view_A,
            dose_e_per_A2=self.dose_e_per_A2,
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
            contrast="phase" if self.potential == "phase" else "adf",
            extra={
                "simulation": {
                    "particle": self.particle,
                    "scale": self.particle_scale,
                    "potential": self.potential,
                    "noise_std": sim.noise_std,
                    "dose_e_per_A2": self.dose_e_per_A2,
                    "peak_to_noise": sim.peak_to_noise,
                    "blur_sigma_A": self.blur_sigma_A,
                    "probe": self.probe or "gaussian",
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
                sim.truth, self.potential, self.pixel_size_A, h, self.particle_atom_sigma_A, self.blur_sigma_A
            )
            np.save(self.output / "potential_volume.npy", volume)
            update_manifest(self.output, volume="potential_volume.npy", volume_voxel_size_A=self.pixel_size_A)
        print(
            f"wrote {self.output}: {len(truth)} atoms, {n} tilts "
            f"({np.min(sim.angles_deg):g}..{np.max(sim.angles_deg):g} deg), "
            f"{h}x{w} px at {self.pixel_size_A} Å, {self.potential} potential, noise {sim.noise_std:g}, peak-to-noise "
            f"{sim.peak_to_noise:.1f}"
        )

    def replicate(self) -> None:
        """``--like DIR``: a replica of a real series (:mod:`gaussian_atoms_method.harness.replica`)."""
        import numpy as np

        from dataparsers.registration_file import read_registration
        from dataparsers.tilt_series_format import load_tilt_series
        from gaussian_atoms_method.atoms.atom_set import read_atoms
        from gaussian_atoms_method.harness.replica import physical_truth, write_replica

        if self.potential == "phase" or self.dose_e_per_A2 is not None:
            raise ValueError(
                "--like draws ADF views of a real series: --potential phase and --dose-e-per-A2 apply to the named "
                "particles"
            )
        if self.noise_over_atom < 1.0 or (self.noise_over_atom > 1.0 and self.noise_sigma_A <= 0):
            raise ValueError(
                f"--noise-over-atom {self.noise_over_atom:g}: expected 1 or more and, above 1, with the atoms' width "
                f"it was read at (--noise-sigma-A, Å > 0; the run prints both)"
            )
        series = load_tilt_series(self.like)
        if Path(self.particle).is_file():
            atoms, origin = read_atoms(self.particle), np.zeros(3)
        elif series.truth_path is not None:
            atoms, origin = read_atoms(series.truth_path), series.origin_A
        else:
            raise ValueError(
                f"--like {self.like}: its series has no truth file; give the atoms as --particle FILE (Å about "
                f"the tilt centre, with species)"
            )
        if atoms.species is None or np.any(atoms.species == "X"):
            raise ValueError("--particle: the replica needs each atom's element (an xyz or csv file with species)")
        if not self.keep_close_pairs:
            kept, bond_A, closest_A = physical_truth(atoms)
            if len(kept) < len(atoms):
                print(
                    f"simulate: {len(atoms) - len(kept)} of the {len(atoms)} atoms lie closer to another than the "
                    f"shortest bond their elements can form ({bond_A:.2f} Å; the closest pair {closest_A:.2f} Å "
                    f"apart): set aside, the truth is the {len(kept)} a specimen can hold (--keep-close-pairs "
                    f"keeps them)"
                )
            atoms = kept
        shifts = None
        if self.shifts_from is not None:
            if self.shift_px:
                raise ValueError("--shifts-from and --shift-px both shift the views: give one")
            shifts = read_registration(self.shifts_from)[0]
            if len(shifts) != series.n_views:
                raise ValueError(
                    f"--shifts-from {self.shifts_from}: {len(shifts)} views' shifts, the series --like {self.like} "
                    f"has {series.n_views} views"
                )
        _, replica = write_replica(
            series,
            atoms,
            self.output,
            origin,
            extra={
                "simulation": {
                    "like": str(self.like),
                    "atoms": len(atoms),
                    "atom_sigma_A": self.particle_atom_sigma_A,
                    "support_A": self.support_A,
                    "potential": self.potential,
                    "probe": self.probe or "aberrated",
                    "optics": dataclasses.asdict(self.optics()),
                    "scan_jitter_px": self.scan_jitter_px,
                    "crop_order": self.crop_order,
                    "noise_over_atom": self.noise_over_atom,
                    "noise_sigma_A": self.noise_sigma_A,
                    "shift_px": self.shift_px,
                    "shifts_from": None if self.shifts_from is None else str(self.shifts_from),
                    "gain_scatter": self.gain_scatter,
                    "seed": self.seed,
                }
            },
            atom_sigma_A=self.particle_atom_sigma_A,
            support_A=self.support_A,
            probe=self.probe or "aberrated",
            potential="gaussian" if self.potential == "gaussian" else "lobato",
            optics=self.optics(),
            scan_jitter_px=self.scan_jitter_px,
            crop_order=self.crop_order,
            noise_over_atom=self.noise_over_atom,
            noise_sigma_A=self.noise_sigma_A,
            blur_sigma_A=self.blur_sigma_A,
            shift_px=self.shift_px,
            gain_scatter=self.gain_scatter,
            seed=self.seed,
            shifts_px=shifts,
        )
        n, h, w = replica.projections.shape
        print(
            f"wrote {self.output}: a replica of {self.like}: {len(atoms)} atoms "
            f"({'Lobato potentials, ADF contrast' if self.potential == 'lobato' else 'Gaussian atoms'}, "
            f"{self.probe or 'aberrated'} probe), {n} views of {h}x{w} px at "
            f"{series.pixel_size_A:g} Å, noise variance {replica.noise.read_var:.4g} + {replica.noise.gain:.4g} x "
            f"signal as read from it"
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
    (an object wider than the field of view; needs --data).  Without it, --data scores the true
    atoms inside the footprint at zero tilt (a film's whole model against one sub-area)."""
    output: Optional[Path] = None
    """Also write the JSON here."""

    def main(self) -> None:
        from gaussian_atoms_method.atoms.atom_set import read_atoms
        from gaussian_atoms_method.atoms.matching import uncount_straddling
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
        no_ssim = ""
        origin, counted = (0.0, 0.0, 0.0), None
        if self.data is not None:
            series, truth, volume, voxel = load_reference(self.data)
            origin = series.origin_A
            if self.interior_A is None and not series.tilt_axis_angle_deg:
                counted = inside_footprint(truth.positions, series, 0.0)  # as the run scores itself
                beside = self.pred.parent / "non_atoms.xyz"  # a run's: those beyond the field, as it scores itself
                if beside.is_file():
                    others = read_atoms(beside).positions
                    beyond = others[~inside_footprint(others, series, 0.0)]
                    counted = uncount_straddling(truth.positions, counted, pred.positions, beyond, self.radius_A)
            if self.interior_A is not None:
                pred, truth = (a.subset(inside_footprint(a.positions, series, self.interior_A)) for a in (pred, truth))
                volume, no_ssim = None, "--interior-A scores part of the volume"  # the volume spans the whole cube
        else:
            truth = read_atoms(self.truth)
        if volume is not None and (pred.sigmas is None or pred.amplitudes is None):
            volume, no_ssim = None, f"{self.pred.name} holds positions without widths and masses (traced atoms)"
        elif self.data is not None and volume is None and not no_ssim:
            no_ssim = f"{self.data} holds no potential volume (simulate --save-volume writes one)"
        scores = evaluate_atoms(
            pred, truth, self.radius_A, self.mean_shift, volume, voxel, origin, true_counted=counted
        )
        if self.output is not None:
            self.output.write_text(json.dumps(scores, indent=2) + "\n")
        print(json.dumps(scores))  # one line on the console: the scores for a program, the summary below for you
        print(summary_line(scores, str(self.pred)), file=sys.stderr)
        if no_ssim:
            print(f"no volume SSIM: {no_ssim}", file=sys.stderr)


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
        from gaussian_atoms_method.atoms.species import classify_species, one_population_note

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
            atoms.element_confidence = report.pop("confidence")
            print(json.dumps({"species": report}))
            if not report.get("separated", True):
                print(one_population_note(report, atoms.species[0]), file=sys.stderr)
        write_atoms(atoms, self.output)
        print(f"wrote {len(atoms)} atoms to {self.output}")


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
class Train:
    """Train on a tilt series with the options of ns-train gaussian-atoms, started sooner
    (gaussian-atoms train -h lists them)."""

    def main(self) -> None:  # the entry point hands "train ..." to train.run before tyro
        raise AssertionError("unreachable")
