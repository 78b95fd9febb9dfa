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
    characteristic of the excursion set (:func:`expected_noise_peaks`) equals the rate.
    ``n_voxels``: the size of the volume the threshold is for, when ``field`` is a sample of the
    same noise on a smaller grid.  ``field``: an array, or a tensor (read on its device).
    """
    return level_for(resolution_elements(field, n_voxels), false_alarm_rate)


def level_for(resels: float, false_alarm_rate: float) -> float:
    """The height (standard deviations) a smooth 3D Gaussian random field of ``resels``
    resolution elements exceeds anywhere with probability about ``false_alarm_rate``
    (:func:`random_field_threshold` for a field already read).

    >>> round(level_for(1000.0, 0.05), 2)
    4.64
    """
    lo, hi = 1.8, 40.0  # (u^2 - 1) exp(-u^2 / 2) falls monotonically beyond sqrt(3)
    if expected_noise_peaks(lo, resels) <= false_alarm_rate:
        return lo
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if expected_noise_peaks(mid, resels) > false_alarm_rate else (lo, mid)
    return hi


def resolution_elements(field, n_voxels: int | None = None) -> float:
    """``R``, the number of resolution elements of a smooth random field (at least one): the
    volume (``n_voxels``, else the field's own) over the product of the field's FWHMs along
    each axis, each read from the field itself as ``sqrt(4 ln 2 var(f) / var(df/dx))`` (voxels;
    exact for smoothed white noise).  ``field``: an array, or a tensor (read on its device)."""
    if isinstance(field, torch.Tensor):  # on its device: only the three variances come back
        f = field.double()
        scale = max(float(f.std(unbiased=False)), 1e-300)
        variances = [float(torch.diff(f, dim=a).var(unbiased=False)) / scale**2 for a in range(f.ndim)]
    else:
        f = np.asarray(field, dtype=np.float64)
        f = (f - f.mean()) / max(f.std(), 1e-300)
        variances = [float(np.var(np.diff(f, axis=a))) for a in range(f.ndim)]
    fwhm = [math.sqrt(4 * math.log(2) / max(v, 1e-300)) for v in variances]
    return max(float(np.prod(f.shape) if n_voxels is None else n_voxels) / float(np.prod(fwhm)), 1.0)


def expected_noise_peaks(u: float, resels: float) -> float:
    """How many peaks a smooth 3D Gaussian random field of ``resels`` resolution elements holds
    above ``u`` standard deviations, for large ``u``: the expected Euler characteristic of the
    excursion set, ``R (4 ln 2)^(3/2) / (2 pi)^2 (u^2 - 1) exp(-u^2 / 2)`` (Worsley et al., Hum.
    Brain Mapp. 1996).

    >>> round(expected_noise_peaks(4.6, 1000.0), 4)
    0.0599
    """
    density = (4 * math.log(2)) ** 1.5 / (2 * math.pi) ** 2
    return resels * density * (u * u - 1.0) * math.exp(-u * u / 2.0)


def discovery_level(heights: np.ndarray, resels: float, rate: float, family_wise: float) -> float:
    """The Benjamini-Hochberg level for peaks of ``heights`` (standard deviations) in a field of
    ``resels``: the lowest height ``h_k`` (the k-th highest) with no more noise peaks expected
    above it than ``rate`` times the ``k`` peaks there (:func:`expected_noise_peaks`), never
    above ``family_wise``.  A value must exceed the level to count; with no such peak it is
    ``family_wise``.

    >>> discovery_level(np.array([9.0, 8.0, 4.4, 2.0]), 1000.0, 0.05, 4.6) < 4.4
    True
    >>> discovery_level(np.array([4.4, 2.0]), 1000.0, 0.05, 4.6)
    4.6
    """
    h = np.sort(np.asarray(heights, dtype=np.float64))[::-1]
    ok = [k for k in range(len(h)) if h[k] > math.sqrt(3.0) and expected_noise_peaks(h[k], resels) <= rate * (k + 1)]
    return min(float(np.nextafter(h[ok[-1]], -np.inf)), family_wise) if ok else family_wise
