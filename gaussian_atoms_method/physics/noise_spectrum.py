"""The views' noise at the atoms' scale, read from the band of their spectrum no atom reaches.

The pre-fit reading (:func:`~gaussian_atoms_method.physics.noise.noise_from_projections`) sees
each pixel's noise through a filter of neighbouring pixels, so it reads the noise near the
sampling's highest frequencies.  Views that were interpolated (a crop, an alignment shift, a
turn to the nominal axis), filtered or denoised hold correlated noise: at those frequencies the
processing has taken part of it away, while an atom, which is broad, sees the noise at low
frequencies, where nothing was taken.  A stack shifted by random sub-pixel amounts with cubic
splines reads 0.54 of its noise there (tests/test_noise.py).

So the views' mean power spectrum (each view's periodic component, Moisan's decomposition, so
that its edges leave no cross) is read in radial bins.  An atom's image falls off steeply with
frequency (a Gaussian of width ``s`` falls as ``exp(-4 pi^2 s^2 f^2)``, steeper than
:data:`STEEPEST_NOISE_FALL` for any atom a pixel samples, ``s`` at least 1 px), the noise slowly
(an interpolation attenuates it towards the Nyquist frequency, never above one): the band from
the last bin that falls steeper than a Gaussian of half a pixel (by three standard errors of the
bins' means) on holds noise alone.  Its fall
from start to end says whether the noise is correlated (:data:`CORRELATED_FALL`).  Where it is,
the band is carried to zero frequency: an interpolation kernel of ``m`` taps along an axis
passes noise power ``|H(f)|^2``, a polynomial of degree ``m - 1`` in ``sin^2(pi f)``, so the log
spectrum is fitted by such polynomials along rows and columns (:func:`band_level`); linear,
cubic and quintic splines at random shifts all read within 5%.  Where the spectrum falls
steeply all the way (atoms finer than the sampling, or views blurred or denoised at every
frequency the atoms leave) the band is not there, and nothing is read.

numpy, or torch on a GPU.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

BIN_WIDTH = 0.025
"""Radial bins of the spectrum, cycles per pixel: 20 bins from zero to Nyquist."""

STEEPEST_NOISE_FALL = 4.0 * math.pi**2 * 0.5**2
"""The steepest fall of the log spectrum per squared frequency (px^2) the noise band may show:
a Gaussian blur of half a pixel's.  An interpolation's kernel is narrower (cubic splines fall by
a quarter from 0.2 to 0.3 cycles/px at the worst shift, about 6 here); an atom's image a pixel
samples is wider (a width of 1 px falls 39.5)."""

LEVEL_BINS = 3
"""The bins at the band's start and at its end whose means tell a falling band from a flat one
(and the band's level where it is flat)."""

INTERPOLATION_DEGREE = 3
"""The degree in ``sin^2(pi f)`` of the band's fit along each axis (:func:`band_level`): exact for
a kernel of four taps (cubic convolution), and the first terms of a spline's."""

CORRELATED_FALL = 1.1
"""The noise is correlated where the band's start lies this many times above its end (its last
:data:`LEVEL_BINS` bins) and by 4 standard errors: white noise is flat there within the bins'
scatter (1-2% on a 29-view stack of 114 px views), and what the atoms leave in the first bins
is under 1%; an interpolation takes 30-100% at Nyquist."""


@dataclass(frozen=True)
class NoiseSpectrum:
    """``level``: the noise power per frequency the atoms see (at zero frequency: the variance
    white noise of the same effect would have, the views' units squared); ``band_start``:
    where the band begins, cycles/px; ``fall``: the band's start over its end (1 for white
    noise); ``correlated``: whether that fall is significant (:data:`CORRELATED_FALL`)."""

    level: float
    band_start: float
    fall: float
    correlated: bool


def periodic_component(image: np.ndarray) -> np.ndarray:
    """(H, W) ``image`` less its mean and its smooth component (L. Moisan, "Periodic plus smooth
    image decomposition", J. Math. Imaging Vis. 39, 161 (2011)): what is left wraps around
    without a jump at the edges, so its spectrum holds no cross from them.

    >>> ramp = np.add.outer(np.arange(16.0), np.zeros(16))  # a jump of 15 where it wraps around
    >>> round(float((periodic_component(ramp) ** 2).sum() / ((ramp - ramp.mean()) ** 2).sum()), 4)
    0.0039
    """
    u = np.asarray(image, dtype=np.float64)
    u = u - u.mean()
    boundary = np.zeros_like(u)
    boundary[0, :] += u[-1, :] - u[0, :]
    boundary[-1, :] += u[0, :] - u[-1, :]
    boundary[:, 0] += u[:, -1] - u[:, 0]
    boundary[:, -1] += u[:, 0] - u[:, -1]
    fy = np.fft.fftfreq(u.shape[0])[:, None]
    fx = np.fft.fftfreq(u.shape[1])[None, :]
    denominator = 2.0 * np.cos(2.0 * np.pi * fy) + 2.0 * np.cos(2.0 * np.pi * fx) - 4.0
    denominator[0, 0] = 1.0
    smooth = np.fft.fft2(boundary) / denominator
    smooth[0, 0] = 0.0
    return u - np.fft.ifft2(smooth).real


def _periodic_power_torch(views, device) -> np.ndarray:
    """(H, W) the summed power spectra of the (V, H, W) views' periodic components
    (:func:`periodic_component`), in torch on ``device``, every view at once."""
    import torch

    u = torch.as_tensor(views, device=device).double()
    u = u - u.mean(dim=(-2, -1), keepdim=True)
    boundary = torch.zeros_like(u)
    boundary[:, 0, :] += u[:, -1, :] - u[:, 0, :]
    boundary[:, -1, :] += u[:, 0, :] - u[:, -1, :]
    boundary[:, :, 0] += u[:, :, -1] - u[:, :, 0]
    boundary[:, :, -1] += u[:, :, 0] - u[:, :, -1]
    h, w = u.shape[-2:]
    fy = torch.fft.fftfreq(h, device=device, dtype=torch.float64)[:, None]
    fx = torch.fft.fftfreq(w, device=device, dtype=torch.float64)[None, :]
    denominator = 2.0 * torch.cos(2.0 * torch.pi * fy) + 2.0 * torch.cos(2.0 * torch.pi * fx) - 4.0
    denominator[0, 0] = 1.0
    smooth = torch.fft.fft2(boundary) / denominator
    smooth[:, 0, 0] = 0.0
    return (torch.fft.fft2(u) - smooth).abs().square().sum(dim=0).cpu().numpy()


def mean_power(projections, device=None) -> np.ndarray:
    """(H, W) the (V, H, W) views' mean power spectrum, their periodic components'
    (:func:`periodic_component`), per frequency (white noise of variance ``v`` reads ``v``), in
    :func:`numpy.fft.fftfreq` order.  In numpy, or in torch on ``device`` (a GPU: the FFTs there)."""
    v, h, w = projections.shape
    if device is not None:
        power = _periodic_power_torch(projections, device)
    else:
        power = np.zeros((h, w))
        for view in np.asarray(projections, dtype=np.float64):
            power += np.abs(np.fft.fft2(periodic_component(view))) ** 2
    return power / (v * h * w)


def _binned(index: np.ndarray, values: list[np.ndarray], n: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """How many of the flat ``index`` fall in each of ``n`` bins, and each of ``values``' mean there."""
    counts = np.bincount(index, minlength=n).astype(np.float64)
    return counts, [np.bincount(index, weights=x, minlength=n) / np.maximum(counts, 1.0) for x in values]


def radial_spectrum(power: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The (H, W) ``power`` (:func:`mean_power`) in radial bins of :data:`BIN_WIDTH` up to
    Nyquist: bin centres (cycles/px), mean powers and how many frequencies each holds."""
    h, w = power.shape
    radius = np.hypot(np.fft.fftfreq(h)[:, None], np.fft.fftfreq(w)[None, :]).ravel()
    n = int(round(0.5 / BIN_WIDTH))
    index = (radius / BIN_WIDTH).astype(np.int64)
    keep = index < n
    counts, (means,) = _binned(index[keep], [power.ravel()[keep]], n)
    return (np.arange(n) + 0.5) * BIN_WIDTH, means, counts


def band_level(power: np.ndarray, band_start: float) -> float:
    """The noise ``power`` (:func:`mean_power`) holds beyond ``band_start`` (cycles/px),
    carried to zero frequency: ``log P = c + sum_k a_k u^k + sum_k b_k v^k``, ``u`` and ``v``
    ``sin^2(pi f)`` along rows and columns, ``k`` to :data:`INTERPOLATION_DEGREE`, fitted by
    least squares over the band in square bins of :data:`BIN_WIDTH` (each weighted by its count);
    ``exp(c)``."""
    h, w = power.shape
    fy = np.abs(np.fft.fftfreq(h))[:, None] + np.zeros(w)
    fx = np.abs(np.fft.fftfreq(w))[None, :] + np.zeros((h, 1))
    n = int(round(0.5 / BIN_WIDTH))
    keep = (np.hypot(fy, fx) >= band_start).ravel()
    row, col = (np.minimum((f / BIN_WIDTH).astype(np.int64), n - 1) for f in (fy, fx))
    index = (row * n + col).ravel()
    u, v = (np.sin(np.pi * f).ravel() ** 2 for f in (fx, fy))
    counts, (p, u, v) = _binned(index[keep], [power.ravel()[keep], u[keep], v[keep]], n * n)
    held = (counts > 0) & (p > 0)
    k = np.arange(1, INTERPOLATION_DEGREE + 1)
    basis = np.column_stack([np.ones(int(held.sum())), u[held, None] ** k, v[held, None] ** k])
    weight = np.sqrt(counts[held])
    coefficients = np.linalg.lstsq(basis * weight[:, None], np.log(p[held]) * weight, rcond=None)[0]
    return float(np.exp(coefficients[0]))


def noise_spectrum(projections, device=None) -> NoiseSpectrum | None:
    """The noise the atoms see, read from the (V, H, W) views' spectrum beyond the atoms (module
    text; ``device`` as :func:`mean_power`'s); None where the spectrum holds no such band.

    White noise of variance 4 (32 views of 64 x 64 pixels: its level reads 0-3% high here, 0-1%
    on 47 views of 271 x 271):

    >>> rng = np.random.default_rng(0)
    >>> white = noise_spectrum(rng.normal(0.0, 2.0, (32, 64, 64)))
    >>> bool(abs(white.level / 4.0 - 1.0) < 0.05), white.correlated
    (True, False)
    """
    power = mean_power(projections, device)
    f, radial, counts = radial_spectrum(power)
    counts = counts * len(projections)
    valid = counts > 0
    f, radial, counts = f[valid], radial[valid], counts[valid]
    if len(f) < 2 * LEVEL_BINS + 3 or np.any(radial <= 0):
        return None
    slopes = np.diff(np.log(radial)) / np.diff(f**2)
    # each bin's mean of exponentially distributed powers: a relative error of 1 / sqrt(count)
    slope_se = np.sqrt(1.0 / counts[:-1] + 1.0 / counts[1:]) / np.diff(f**2)
    steep = np.flatnonzero(slopes < -STEEPEST_NOISE_FALL - 3.0 * slope_se)  # steeper by 3 standard errors
    first = int(steep[-1]) + 2 if len(steep) else 1  # past the last steep fall and the bin it ends in
    if len(f) - first < 2 * LEVEL_BINS:
        return None
    start, end = slice(first, first + LEVEL_BINS), slice(len(f) - LEVEL_BINS, len(f))
    head, last = (float(np.average(radial[s], weights=counts[s])) for s in (start, end))
    se = math.hypot(1.0 / math.sqrt(counts[start].sum()), 1.0 / math.sqrt(counts[end].sum()))
    fall = head / last
    correlated = fall > CORRELATED_FALL and math.log(fall) > 4.0 * se
    band_start = float(f[first] - BIN_WIDTH / 2)
    level = band_level(power, band_start) if correlated else head
    return NoiseSpectrum(level, band_start, fall, bool(correlated))
