"""Peaks in a voxel volume: local maxima, keeping the strongest of those closer than a
distance, and the height a noise field's peaks stay below.  Shared by the start from a back-projection
(:mod:`.candidates`) and the baselines'
atom tracing (:mod:`gaussian_atoms_method.harness.tracing`)."""

from __future__ import annotations

import math

import numpy as np
import torch


def parabola_vertex(below: np.ndarray, centre: np.ndarray, above: np.ndarray) -> np.ndarray:
    """Offset (voxels) of the vertex of the parabola through three equally spaced values, clipped
    to half a voxel; 0 where the three are not concave (no maximum between them)."""
    curvature = below - 2 * centre + above
    concave = curvature < 0
    return np.where(concave, 0.5 * (below - above) / np.where(concave, curvature, -1.0), 0.0).clip(-0.5, 0.5)


def random_field_threshold(field: np.ndarray, false_alarm_rate: float = 0.05, n_voxels: int | None = None) -> float:
    """The height ``u`` (in standard deviations) that a smooth 3D Gaussian random field exceeds
    anywhere with probability about ``false_alarm_rate``: where the expected Euler
    characteristic of the excursion set, ``R (4 ln 2)^(3/2) / (2 pi)^2 (u^2 - 1) exp(-u^2 / 2)``
    (Worsley et al., Hum. Brain Mapp. 1996), equals the rate.  ``R``, the number of resolution
    elements, is the volume over the product of the field's FWHMs along each axis, each read
    from the field itself as ``sqrt(4 ln 2 var(f) / var(df/dx))`` (voxels; exact for smoothed
    white noise).  ``n_voxels``: the size of the volume the threshold is for, when ``field``
    is a sample of the same noise on a smaller grid.  ``field``: an array, or a tensor (read
    on its device).
    """
    if isinstance(field, torch.Tensor):  # on its device: only the three variances come back
        f = field.double()
        scale = max(float(f.std(unbiased=False)), 1e-300)
        variances = [float(torch.diff(f, dim=a).var(unbiased=False)) / scale**2 for a in range(f.ndim)]
    else:
        f = np.asarray(field, dtype=np.float64)
        f = (f - f.mean()) / max(f.std(), 1e-300)
        variances = [float(np.var(np.diff(f, axis=a))) for a in range(f.ndim)]
    fwhm = [math.sqrt(4 * math.log(2) / max(v, 1e-300)) for v in variances]
    resels = max(float(np.prod(f.shape) if n_voxels is None else n_voxels) / float(np.prod(fwhm)), 1.0)
    density = (4 * math.log(2)) ** 1.5 / (2 * math.pi) ** 2

    def expected(u):
        return resels * density * (u * u - 1.0) * math.exp(-u * u / 2.0)

    lo, hi = 1.8, 40.0  # (u^2 - 1) exp(-u^2 / 2) falls monotonically beyond sqrt(3)
    if expected(lo) <= false_alarm_rate:
        return lo
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if expected(mid) > false_alarm_rate else (lo, mid)
    return hi
