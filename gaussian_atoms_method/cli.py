"""``gaussian-atoms <verb>``: one tyro CLI whose verbs call the physics core.

Verbs: ``simulate`` (write a tilt-series directory with known atoms) and ``evaluate`` (score
predicted atoms against the truth).  Training is ``ns-train gaussian-atoms``.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal, Union

import tyro


@dataclass
class Simulate:
    """Simulate a tilt series with known atoms and write a tilt_series.json directory."""

    output: Path = Path("data/sim")
    """Directory to write (tilt_series.json, projections.npy, angles.txt, atoms_true.xyz)."""
    particle: str = "au"
    """au, fept, apd, hea, sphere (an fcc sphere of --element, --radius-A) or a structure file."""
    scale: float = 1.0
    """Linear size factor (atom count ~ scale^3) for small versions of the named particles."""
    element: str = "Au"
    """Element of the fcc sphere (--particle sphere)."""
    radius_A: float = 10.0
    """Radius of the fcc sphere, Å (--particle sphere)."""
    potential: Literal["lobato", "gaussian"] = "lobato"
    """abTEM Lobato projected potential (independent physics), or the quick Gaussian model."""
    tilts: str = "limited"
    """Tilt scheme: full (-90:1:90), limited (-70:3:68), sampled, wedge, 'start:step:stop' or a comma list (deg)."""
    pixel_size_A: float = 0.25
    atom_sigma_A: float = 0.35
    """Width of each atom of the Gaussian potential, Å (--potential gaussian)."""
    blur_sigma_A: float = 0.5
    """Gaussian probe blur, Å."""
    noise_std: float = 50.0
    """Standard deviation of the additive Gaussian noise, projection units (V·Å for Lobato)."""
    tilt_axis: Literal["x", "y"] = "y"
    seed: int = 0

    def main(self) -> None:
        import numpy as np

        from dataparsers.tilt_series_format import write_tilt_series

        from .particles import make_particle
        from .simulate import parse_tilts, simulate_tilt_series, spherical_particle

        if self.particle == "sphere":
            particle = spherical_particle(self.element, self.radius_A)
        else:
            particle = make_particle(self.particle, self.scale, self.seed)
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
                    "scale": self.scale,
                    "potential": self.potential,
                    "noise_std": self.noise_std,
                    "peak_to_noise": sim.peak_to_noise,
                    "blur_sigma_A": self.blur_sigma_A,
                    "seed": self.seed,
                }
            },
        )
        n, h, w = sim.projections.shape
        print(
            f"wrote {self.output}: {len(truth)} atoms, {n} tilts ({np.min(sim.angles_deg):g}..{np.max(sim.angles_deg):g} deg), "
            f"{h}x{w} px at {self.pixel_size_A} Å, {self.potential} potential, noise {self.noise_std:g}, peak-to-noise {sim.peak_to_noise:.1f}"
        )


@dataclass
class Evaluate:
    """Score predicted atoms against the truth (JSON to stdout)."""

    pred: Path
    """Predicted atoms (xyz/extxyz/csv or any ASE format)."""
    truth: Path
    """True atoms."""
    radius_A: float = 0.75
    """A true atom is found if a predicted atom lies within this distance (Å)."""

    def main(self) -> None:
        from .atoms import read_atoms
        from .metrics import score_atoms

        scores = score_atoms(read_atoms(self.pred).positions, read_atoms(self.truth).positions, self.radius_A)
        print(json.dumps(scores, indent=2))


Commands = Union[
    Annotated[Simulate, tyro.conf.subcommand("simulate")],
    Annotated[Evaluate, tyro.conf.subcommand("evaluate")],
]


def entrypoint(argv: list[str] | None = None) -> None:
    """Run one verb; errors in the user's input are reported in one line, exit status 2."""
    from dataparsers.tilt_series_format import TiltSeriesError

    from .atoms import AtomFileError

    command = tyro.cli(Commands, args=argv)
    try:
        command.main()
    except (TiltSeriesError, AtomFileError, ValueError) as exc:
        print(f"gaussian-atoms: error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None


if __name__ == "__main__":
    entrypoint()
