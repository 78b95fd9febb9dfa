"""The accuracy table's options, declared once: the harness's
:class:`~gaussian_atoms_method.harness.benchmark.AccuracyBenchmark` and the command
``gaussian-atoms benchmark-accuracy`` both take them (plain dataclass fields: importing this
imports nothing heavy, so the command line starts no slower for it)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal


@dataclass
class AccuracyOptions:
    """Which cells of the table (particles x tilt schemes x noise levels x methods), and how."""

    output: Path = Path("outputs/benchmark-accuracy")
    """The table's folder: the simulated data, each method's runs, results.csv, results.md and the figures."""
    particles: tuple[str, ...] = ("au",)
    tilts: tuple[str, ...] = ("full", "limited")
    noise: tuple[float, ...] = (50.0, 200.0, 500.0)
    methods: tuple[str, ...] = ("fbp", "sart", "ours")
    iterations: int = 3000
    """Training iterations of our method."""
    device: Literal["cpu", "cuda"] = "cpu"
    pixel_size_A: float = 0.25
    """Detector pixel size of the simulated projections, Å."""
    noise_kind: Literal["gaussian", "poisson"] = "gaussian"
    """``gaussian``: each noise level is the standard deviation of additive noise (projection
    units); ``poisson``: each is the dose as the expected counts at the brightest pixel, the
    projections drawn as Poisson counts of ``1 + dose x clean / max(clean)`` (a floor of one
    count, as the peer's aSi-208 data)."""
