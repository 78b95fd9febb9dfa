"""What fitting each atom's true profile instead of one Gaussian could gain: precision and bias.

An atom's image is its projected potential (Lobato's, to the contrast's power) through the
contrast's transfer (an ADF probe with rings and a source, or a phase image's aperture double
overlap and source), not a Gaussian.  Two numbers say what a learned profile could buy:

* precision: the variance of a one-Gaussian least-squares fit of an isolated atom's position
  under white noise against the information bound of a fit with the true profile,
  ``(int g_x^2)(int p_x^2) / (int g_x p_x)^2 >= 1`` (``p`` the image, ``g`` its least-squares
  Gaussian, ``_x`` the derivative along x);
* bias: the error in the separation of a bonded pair (noise-free 2D images) that two Gaussians
  of one width make where the tails of one atom reach the other.

Usage::

    python scripts/studies/atom_profile_gain.py

Prints a table; nothing is saved.  Results: docs/studies/atom_profile_gain.md.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.optimize import least_squares

from gaussian_atoms_method.physics.adf import adf_kernel_transform
from gaussian_atoms_method.physics.microscope import DEFAULT_OPTICS
from gaussian_atoms_method.physics.probe_width import contrast_transfer, least_squares_width_A

GRID_PX, SPACING_A = 256, 0.05
CASES = (("phase", 0.7, "C"), ("phase", 0.0, "C"), ("adf", 0.7, "C"), ("adf", 0.7, "Pd"), ("adf", 0.0, "Pd"))
SEPARATIONS_A = (1.42, 1.54, 2.0, 2.5, 3.0)


def atom_spectrum(contrast: str, source_fwhm_A: float, element: str) -> np.ndarray:
    """(GRID_PX, GRID_PX) the spectrum of one atom's image at the origin (numpy's FFT order)."""
    optics = dataclasses.replace(DEFAULT_OPTICS, source_fwhm_A=source_fwhm_A)
    transfer, power = contrast_transfer(optics, contrast)
    k, kernel = adf_kernel_transform(element, power=power)
    fy, fx = np.meshgrid(*(np.fft.fftfreq(GRID_PX, SPACING_A),) * 2, indexing="ij")
    return np.interp(np.hypot(fx, fy), k, kernel, right=0.0) * transfer((GRID_PX, GRID_PX), SPACING_A)


def variance_ratio(spectrum: np.ndarray) -> tuple[float, float]:
    """(the least-squares Gaussian's width in Å, its position variance over the profile's bound)."""
    fx = np.fft.fftfreq(GRID_PX, SPACING_A)[None, :]
    image, slope = np.fft.ifft2(spectrum).real, np.fft.ifft2(spectrum * 2j * np.pi * fx).real
    width = least_squares_width_A(np.fft.fftshift(image))
    at = np.fft.fftfreq(GRID_PX) * GRID_PX * SPACING_A
    y, x = np.meshgrid(at, at, indexing="ij")
    gauss = np.exp(-(x**2 + y**2) / (2 * width**2))
    gauss *= (gauss * image).sum() / (gauss * gauss).sum()
    gauss_slope = -x / width**2 * gauss
    return width, float((gauss_slope**2).sum() * (slope**2).sum() / (gauss_slope * slope).sum() ** 2)


def pair_separation_error_pm(spectrum: np.ndarray, separation_A: float) -> float:
    """The separation two Gaussians of one width fit to a pair's noise-free image, less the truth."""
    fx = np.fft.fftfreq(GRID_PX, SPACING_A)[None, :]
    shift = np.exp(-1j * np.pi * fx * separation_A)
    image = np.fft.fftshift(np.fft.ifft2(spectrum * (shift + shift.conj())).real)
    at = (np.arange(GRID_PX) - GRID_PX // 2) * SPACING_A
    y, x = np.meshgrid(at, at, indexing="ij")

    def misfit(p):
        x1, x2, width, a1, a2 = p
        both = sum(a * np.exp(-((x - c) ** 2 + y**2) / (2 * width**2)) for c, a in ((x1, a1), (x2, a2)))
        return (both - image).ravel()

    peak = image.max()
    start = [-separation_A / 2, separation_A / 2, 0.5, peak, peak]
    fit = least_squares(misfit, start, x_scale=[0.1, 0.1, 0.1, peak, peak])
    return 100.0 * (fit.x[1] - fit.x[0] - separation_A)


def main() -> None:
    import argparse

    argparse.ArgumentParser(description=__doc__.split("\n\n")[0]).parse_args()
    print("| contrast | source FWHM (Å) | element | fitted width (Å) | position std, Gaussian / profile | "
          + " | ".join(f"pair at {d:g} Å (pm)" for d in SEPARATIONS_A) + " |")  # fmt: skip
    print("| --- " * (5 + len(SEPARATIONS_A)) + "|")
    for contrast, source, element in CASES:
        spectrum = atom_spectrum(contrast, source, element)
        width, ratio = variance_ratio(spectrum)
        errors = [pair_separation_error_pm(spectrum, d) for d in SEPARATIONS_A]
        print(f"| {contrast} | {source:g} | {element} | {width:.3f} | {np.sqrt(ratio):.3f} | "
              + " | ".join(f"{e:+.1f}" for e in errors) + " |")  # fmt: skip


if __name__ == "__main__":
    main()
