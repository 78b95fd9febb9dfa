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

from dataclasses import dataclass

import numpy as np

ELECTRON_WAVELENGTH_300KV_A = 0.019687
"""Relativistic electron wavelength at 300 kV, Å."""


def electron_wavelength_A(voltage_kV: float) -> float:
    """The relativistic electron wavelength at an accelerating voltage, Å.

    >>> round(electron_wavelength_A(300.0), 6)
    0.019687
    """
    h, m0, e, c = 6.62607015e-34, 9.1093837015e-31, 1.602176634e-19, 2.99792458e8
    v = voltage_kV * 1e3
    return float(h / np.sqrt(2 * m0 * e * v * (1 + e * v / (2 * m0 * c**2))) * 1e10)


def aberrated_probe_intensity(
    pixel_size_A: float,
    size_px: int = 65,
    semiangle_mrad: float = 20.0,
    defocus_A: float = 40.0,
    cs_A: float = 1e5,
    wavelength_A: float = ELECTRON_WAVELENGTH_300KV_A,
    source_fwhm_A: float = 0.0,
    halo_fraction: float = 0.0,
    halo_hwhm_A: float = 2.0,
) -> np.ndarray:
    """(size_px, size_px) probe intensity on the detector grid, centred at ``size_px // 2``, unit sum.

    ``size_px`` odd: the centre is then the middle pixel, where a same-size convolution
    (:func:`convolve_views`) puts the image of a point (an even size shifted the harness's
    carbon series by a pixel: its atoms came out 0.46 Å off).

    Defaults: 20 mrad at 300 kV (a 0.6 Å Airy core), 40 Å defocus and 10 µm Cs: the core keeps
    about 60% of the intensity, the rest is rings and tails out to a few Å.

    The coherent probe is then spread by the effective source: a Gaussian of ``source_fwhm_A``
    (the demagnified source of a field-emission gun, 0.5-1 Å in an aberration-corrected STEM),
    and a share ``halo_fraction`` of the intensity moved into a Lorentzian halo of half width
    ``halo_hwhm_A`` (the long-range part of the effective source, Dwyer et al.'s measurement;
    incoherent scattering in the specimen adds to it), truncated at the kernel's edge.
    """
    k = np.fft.fftfreq(size_px, d=pixel_size_A)
    k2 = k[:, None] ** 2 + k[None, :] ** 2
    aperture = np.sqrt(k2) * wavelength_A <= semiangle_mrad * 1e-3
    chi = np.pi * wavelength_A * defocus_A * k2 + 0.5 * np.pi * cs_A * wavelength_A**3 * k2**2
    psi = np.fft.ifft2(aperture * np.exp(-1j * chi))
    intensity = np.abs(psi) ** 2
    if source_fwhm_A > 0:  # a Gaussian source: the intensity's transform times the source's
        sigma = source_fwhm_A / (2.0 * np.sqrt(2.0 * np.log(2.0)))
        intensity = np.fft.ifft2(np.fft.fft2(intensity) * np.exp(-2.0 * np.pi**2 * sigma**2 * k2)).real
    intensity = np.fft.fftshift(np.clip(intensity, 0.0, None))
    intensity /= intensity.sum()
    if halo_fraction > 0:
        r = (np.arange(size_px) - size_px // 2) * pixel_size_A
        halo = 1.0 / (1.0 + (r[:, None] ** 2 + r[None, :] ** 2) / halo_hwhm_A**2) ** 1.5  # a 2D Lorentzian
        intensity = (1.0 - halo_fraction) * intensity + halo_fraction * halo / halo.sum()
    return intensity


@dataclass(frozen=True)
class ProbeOptics:
    """A STEM probe by its optics (:func:`aberrated_probe_intensity`): voltage, convergence
    semi-angle, defocus, spherical aberration, the effective source and its halo."""

    voltage_kV: float = 300.0
    semiangle_mrad: float = 20.0
    defocus_A: float = 40.0
    cs_A: float = 1e5
    source_fwhm_A: float = 0.0
    halo_fraction: float = 0.0
    halo_hwhm_A: float = 2.0

    def transfer(self, shape: tuple[int, int], spacing_A: float) -> np.ndarray:
        """The probe intensity's Fourier transform on a periodic grid of ``shape`` and pitch
        ``spacing_A`` (numpy's FFT order, 1 at zero frequency): what multiplies a view's spectrum."""
        k_rows = np.fft.fftfreq(shape[0], d=spacing_A)
        k_cols = np.fft.fftfreq(shape[1], d=spacing_A)
        k2 = k_rows[:, None] ** 2 + k_cols[None, :] ** 2
        wavelength = electron_wavelength_A(self.voltage_kV)
        aperture = np.sqrt(k2) * wavelength <= self.semiangle_mrad * 1e-3
        chi = np.pi * wavelength * self.defocus_A * k2 + 0.5 * np.pi * self.cs_A * wavelength**3 * k2**2
        intensity = np.abs(np.fft.ifft2(aperture * np.exp(-1j * chi))) ** 2
        transfer = np.fft.fft2(intensity / intensity.sum())
        if self.source_fwhm_A > 0:
            sigma = self.source_fwhm_A / (2.0 * np.sqrt(2.0 * np.log(2.0)))
            transfer = transfer * np.exp(-2.0 * np.pi**2 * sigma**2 * k2)
        if self.halo_fraction > 0:
            rows = np.fft.fftfreq(shape[0], d=1.0 / shape[0]) * spacing_A  # signed distances, FFT order
            cols = np.fft.fftfreq(shape[1], d=1.0 / shape[1]) * spacing_A
            halo = 1.0 / (1.0 + (rows[:, None] ** 2 + cols[None, :] ** 2) / self.halo_hwhm_A**2) ** 1.5
            transfer = (1.0 - self.halo_fraction) * transfer + self.halo_fraction * np.fft.fft2(halo / halo.sum())
        return transfer

    def intensity(self, pixel_size_A: float, size_px: int = 65) -> np.ndarray:
        """(size_px, size_px) unit-sum intensity on a detector of ``pixel_size_A``."""
        return aberrated_probe_intensity(
            pixel_size_A,
            size_px,
            self.semiangle_mrad,
            self.defocus_A,
            self.cs_A,
            electron_wavelength_A(self.voltage_kV),
            self.source_fwhm_A,
            self.halo_fraction,
            self.halo_hwhm_A,
        )


def gaussian_transfer(sigma_A: float, shape: tuple[int, int], spacing_A: float) -> np.ndarray:
    """A Gaussian probe's transfer (width ``sigma_A``) on a periodic grid (numpy's FFT order)."""
    k2 = np.fft.fftfreq(shape[0], d=spacing_A)[:, None] ** 2 + np.fft.fftfreq(shape[1], d=spacing_A)[None, :] ** 2
    return np.exp(-2.0 * np.pi**2 * sigma_A**2 * k2)


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
