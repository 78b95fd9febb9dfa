"""The measured views a fit trains on, read once: the tilt series, its normalised projections,
the views' poses, the normalisation between Å and the fit's units, the pixel size and the truth
file.  The fit's functions read them here, not from the dataparser's metadata."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from gaussian_atoms_method.physics.units import Normalisation


@dataclass(frozen=True)
class ViewSet:
    """``series``: the :class:`~dataparsers.tilt_series_format.TiltSeries` (None for a model
    built without data); ``projections``: (V, H, W) in normalised units; ``view_c2w``: (V, 3, 4)
    poses; ``normalisation``: None where the data give none; ``pixel_size_A``; ``truth_path``."""

    series: object | None = None
    projections: torch.Tensor | None = None
    view_c2w: torch.Tensor | None = None
    normalisation: Normalisation | None = None
    pixel_size_A: float | None = None
    truth_path: Path | None = None

    @classmethod
    def from_metadata(cls, metadata: dict | None) -> ViewSet:
        """The views a dataparser's ``metadata`` carries (keys ``tilt_series``, ``projections``,
        ``view_c2w``, ``normalisation``, ``pixel_size_A``, ``truth_path``; any may be missing)."""
        m = metadata or {}
        truth = m.get("truth_path")
        return cls(
            m.get("tilt_series"),
            m.get("projections"),
            m.get("view_c2w"),
            m.get("normalisation"),
            m.get("pixel_size_A"),
            Path(truth) if truth is not None else None,
        )
