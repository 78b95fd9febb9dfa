"""The paper's normalisation: data scaled to [0, 256], the volume to [-0.5, 0.5].

Training runs in normalised units so that learning rates and thresholds mean the same for
every particle; :class:`Normalisation` converts back so that every output is in Å.

* Lengths: ``r_norm = r_A * length_scale`` with ``length_scale = 1 / (max(H, W) * pixel_size_A)``:
  the detector's longer side spans [-0.5, 0.5].
* Projection values: ``p_norm = p * data_scale`` with ``data_scale = 256 / max|p|``.
* A Gaussian ``q_norm exp(-|r_norm|^2 / 2 sigma_norm^2)`` whose line integral (in normalised
  length) reproduces ``p_norm`` has, in physical units, width ``sigma_A = sigma_norm /
  length_scale`` and 3D peak ``q = q_norm * length_scale / data_scale`` (projection units per Å).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

DATA_RANGE = 256.0


@dataclass(frozen=True)
class Normalisation:
    """Maps between physical (Å, input projection units) and normalised training units."""

    length_scale: float  # normalised length per Å
    data_scale: float  # normalised projection value per input unit
    origin_A: tuple[float, float, float] = (0.0, 0.0, 0.0)  # tilt centre in the output frame, Å

    @classmethod
    def for_tilt_series(cls, projections: np.ndarray, pixel_size_A: float, origin_A=(0.0, 0.0, 0.0)) -> "Normalisation":
        """The paper's normalisation of an ``(N, H, W)`` stack with the given pixel size."""
        h, w = projections.shape[1:]
        peak = float(np.abs(projections).max())
        if peak == 0:
            raise ValueError("projections are all zero: there is nothing to reconstruct")
        return cls(1.0 / (max(h, w) * pixel_size_A), DATA_RANGE / peak, tuple(float(o) for o in origin_A))

    def positions_to_A(self, positions_norm: np.ndarray) -> np.ndarray:
        """(N, 3) normalised positions -> Å in the output frame."""
        return np.asarray(positions_norm) / self.length_scale + np.asarray(self.origin_A)

    def positions_from_A(self, positions_A: np.ndarray) -> np.ndarray:
        """(N, 3) Å in the output frame -> normalised positions."""
        return (np.asarray(positions_A) - np.asarray(self.origin_A)) * self.length_scale

    def sigmas_to_A(self, sigmas_norm: np.ndarray) -> np.ndarray:
        return np.asarray(sigmas_norm) / self.length_scale

    def amplitudes_to_physical(self, amplitudes_norm: np.ndarray) -> np.ndarray:
        """3D peaks in input projection units per Å."""
        return np.asarray(amplitudes_norm) * self.length_scale / self.data_scale

    def to_dict(self) -> dict:
        return {"length_scale": self.length_scale, "data_scale": self.data_scale, "origin_A": list(self.origin_A)}


def normalised_projections(series) -> tuple[Normalisation, np.ndarray]:
    """A tilt series' normalisation (:meth:`Normalisation.for_tilt_series`) and its (V, H, W)
    projections in normalised data units (float32): what the dataparser hands the model."""
    normalisation = Normalisation.for_tilt_series(series.projections, series.pixel_size_A, series.origin_A)
    return normalisation, series.projections * np.float32(normalisation.data_scale)
