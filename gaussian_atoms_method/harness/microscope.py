"""What a real microscope adds to the ideal projections: a probe that is not a Gaussian and a
floor that is not flat.

* :func:`aberrated_probe_intensity`: the intensity of a STEM probe formed by a round aperture
  with defocus and spherical aberration, ``|IFFT(A(k) exp(-i chi(k)))|^2`` with
  ``chi = pi lambda df k^2 + pi/2 Cs lambda^3 k^4``: a sharp core with rings and tails that no
  Gaussian has (the image of a point is this kernel, normalised to unit sum);
* :func:`add_varying_floor`: per view, a constant level plus a tilted plane (a support film,
  carbon contamination, a phase image's offset), given as fractions of a column's value.

Pure numpy/scipy, used by :func:`~gaussian_atoms_method.harness.simulate.simulate_tilt_series`.
"""

from __future__ import annotations

import numpy as np

ELECTRON_WAVELENGTH_300KV_A = 0.019687
"""Relativistic electron wavelength at 300 kV, Å."""


def aberrated_probe_intensity(
    pixel_size_A: float,
    size_px: int = 65,
    semiangle_mrad: float = 20.0,
    defocus_A: float = 40.0,
    cs_A: float = 1e5,
    wavelength_A: float = ELECTRON_WAVELENGTH_300KV_A,
) -> np.ndarray:
    """(size_px, size_px) probe intensity on the detector grid, centred at ``size_px // 2``, unit sum.

    ``size_px`` odd: the centre is then the middle pixel, where a same-size convolution
    (:func:`convolve_views`) puts the image of a point (an even size shifted the harness's
    carbon series by a pixel: its atoms came out 0.46 Å off).

    Defaults: 20 mrad at 300 kV (a 0.6 Å Airy core), 40 Å defocus and 10 µm Cs: the core keeps
    about 60% of the intensity, the rest is rings and tails out to a few Å.
    """
    k = np.fft.fftfreq(size_px, d=pixel_size_A)
    k2 = k[:, None] ** 2 + k[None, :] ** 2
    aperture = np.sqrt(k2) * wavelength_A <= semiangle_mrad * 1e-3
    chi = np.pi * wavelength_A * defocus_A * k2 + 0.5 * np.pi * cs_A * wavelength_A**3 * k2**2
    psi = np.fft.ifft2(aperture * np.exp(-1j * chi))
    intensity = np.fft.fftshift(np.abs(psi) ** 2)
    return intensity / intensity.sum()


def convolve_views(projections: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """Each (H, W) view of ``projections`` (N, H, W) convolved with ``kernel`` (centred), same size."""
    from scipy.signal import fftconvolve

    return fftconvolve(
        np.asarray(projections, dtype=np.float64), np.asarray(kernel, dtype=np.float64)[None], mode="same", axes=(1, 2)
    )


def add_varying_floor(projections: np.ndarray, level_fraction: float, variation: float, seed: int = 0) -> np.ndarray:
    """``projections`` (N, H, W) plus, per view, ``level * (1 + variation * plane)``: ``level`` is
    ``level_fraction`` of a column's value (the 99.9th percentile of the clean projections) and
    ``plane`` a unit ramp across the view in a random direction (from -1 to 1 corner to corner)."""
    p = np.asarray(projections, dtype=np.float64)
    level = level_fraction * float(np.percentile(p, 99.9))
    n, h, w = p.shape
    rows = np.linspace(-1.0, 1.0, h)[:, None]
    cols = np.linspace(-1.0, 1.0, w)[None, :]
    angle = np.random.default_rng(seed).uniform(0.0, 2.0 * np.pi, n)
    plane = (np.cos(angle)[:, None, None] * rows + np.sin(angle)[:, None, None] * cols) / np.sqrt(2.0)
    return p + level * (1.0 + variation * plane)
