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

import functools
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
    transfer = _probe_transfer(
        (size_px, size_px), pixel_size_A, semiangle_mrad, defocus_A, cs_A, wavelength_A, source_fwhm_A, halo_fraction,
        halo_hwhm_A,
    )  # fmt: skip
    intensity = np.fft.fftshift(np.clip(np.fft.ifft2(transfer).real, 0.0, None))
    return intensity / intensity.sum()


def squared_frequencies(shape: tuple[int, int], spacing_A: float) -> np.ndarray:
    """(rows, cols) squared spatial frequencies (1/Å²) of a periodic grid, numpy's FFT order."""
    return np.fft.fftfreq(shape[0], d=spacing_A)[:, None] ** 2 + np.fft.fftfreq(shape[1], d=spacing_A)[None, :] ** 2


def _probe_transfer(
    shape, spacing_A, semiangle_mrad, defocus_A, cs_A, wavelength_A, source_fwhm_A, halo_fraction, halo_hwhm_A
) -> np.ndarray:
    """The probe intensity's Fourier transform on a periodic grid (numpy's FFT order, 1 at zero
    frequency): the coherent probe ``|IFFT(A exp(-i chi))|^2`` of unit sum, times a Gaussian
    source's transform, a share moved into a Lorentzian halo (:func:`aberrated_probe_intensity`)."""
    k2 = squared_frequencies(shape, spacing_A)
    aperture = np.sqrt(k2) * wavelength_A <= semiangle_mrad * 1e-3
    chi = np.pi * wavelength_A * defocus_A * k2 + 0.5 * np.pi * cs_A * wavelength_A**3 * k2**2
    intensity = np.abs(np.fft.ifft2(aperture * np.exp(-1j * chi))) ** 2
    transfer = np.fft.fft2(intensity / intensity.sum())
    if source_fwhm_A > 0:
        transfer = transfer * gaussian_transfer(source_fwhm_A / (2.0 * np.sqrt(2.0 * np.log(2.0))), shape, spacing_A)
    if halo_fraction > 0:
        rows = np.fft.fftfreq(shape[0], d=1.0 / shape[0]) * spacing_A  # signed distances, FFT order
        cols = np.fft.fftfreq(shape[1], d=1.0 / shape[1]) * spacing_A
        halo = 1.0 / (1.0 + (rows[:, None] ** 2 + cols[None, :] ** 2) / halo_hwhm_A**2) ** 1.5  # a 2D Lorentzian
        transfer = (1.0 - halo_fraction) * transfer + halo_fraction * np.fft.fft2(halo / halo.sum())
    return transfer


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
        return _probe_transfer(shape, spacing_A, *self._optics())

    def intensity(self, pixel_size_A: float, size_px: int = 65) -> np.ndarray:
        """(size_px, size_px) unit-sum intensity on a detector of ``pixel_size_A``."""
        return aberrated_probe_intensity(pixel_size_A, size_px, *self._optics())

    def _optics(self) -> tuple:
        """semi-angle, defocus, Cs, wavelength, source, halo and its width, in the order
        :func:`aberrated_probe_intensity` takes them."""
        wavelength = electron_wavelength_A(self.voltage_kV)
        return (self.semiangle_mrad, self.defocus_A, self.cs_A, wavelength, self.source_fwhm_A, self.halo_fraction,
                self.halo_hwhm_A)  # fmt: skip


DEFAULT_OPTICS = ProbeOptics(source_fwhm_A=0.7)
"""A 300 kV probe of 20 mrad at 40 Å defocus and 10 µm Cs (rings and tails), spread by an
effective source of 0.7 Å (the middle of an aberration-corrected field-emission STEM's 0.5-1 Å)."""


def gaussian_transfer(sigma_A: float, shape: tuple[int, int], spacing_A: float) -> np.ndarray:
    """A Gaussian probe's transfer (width ``sigma_A``) on a periodic grid (numpy's FFT order)."""
    return np.exp(-2.0 * np.pi**2 * sigma_A**2 * squared_frequencies(shape, spacing_A))


def band_limit(pixel_size_A: float):
    """``transfer(shape, spacing_A)``: no probe, only the band a detector of ``pixel_size_A`` holds
    (1 up to its Nyquist frequency, 0 beyond): atoms drawn through it are drawn as sharp as the
    detector can show them, with nothing to alias.

    >>> band_limit(0.5)((8, 8), 0.25)[0].tolist()  # Nyquist 1 / Å; frequencies 0, 0.5, ... on this grid
    [1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 1.0, 1.0]
    """
    nyquist2 = (0.5 / pixel_size_A) ** 2
    return lambda shape, spacing_A: (squared_frequencies(shape, spacing_A) <= nyquist2) * 1.0


def probe_transfer(probe: str, optics: ProbeOptics, blur_sigma_A: float):
    """``probe(shape, spacing_A)``, the named probe's transfer: ``"aberrated"`` from ``optics``,
    ``"gaussian"`` a Gaussian of ``blur_sigma_A``; a ValueError for any other name."""
    if probe == "aberrated":
        return optics.transfer
    if probe == "gaussian":
        return functools.partial(gaussian_transfer, blur_sigma_A)
    raise ValueError(f"probe must be 'gaussian' or 'aberrated', got {probe!r}")


def misregistered(views: np.ndarray, shifts_px: np.ndarray, gains: np.ndarray) -> np.ndarray:
    """``views`` (V, H, W), in place, each moved by its shift (V, 2) (pixels, rows and columns;
    cubic splines, edges held) and scaled by its gain (V,): a series' misregistration."""
    from scipy import ndimage

    for v in range(len(views)):
        if np.any(shifts_px[v]):
            views[v] = ndimage.shift(views[v], shifts_px[v], order=3, mode="nearest")
        views[v] *= gains[v]
    return views


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
