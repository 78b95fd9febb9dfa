"""A replica's probe as wide as the views' atoms: the effective source that gives one atom's ADF
image the width the fit reads on the measured views.

A run's own replica (:mod:`~gaussian_atoms_method.engine.own_floor`) draws its atoms through a
probe with rings and tails (:data:`~.microscope.DEFAULT_OPTICS`) to learn what a bias alike in
every view does to its fit.  The probe is an assumption, but its width need not be: the fitted
atoms show how wide an atom is in these views.  A probe wider than the views' atoms makes bonded
neighbours overlap far more than they do, and the replica's refit errs by that overlap, not by
the views' physics.  Measured on carbon ptychographic phase images (1,512 atoms, 10,000 e/Å², atoms
fitted 0.55 Å wide): with the fixed 0.7 Å source the replica's refit erred 14/13/17 pm (x/y/z),
five times the fit's own errors, and its floor opened every atom in depth.

So the source size is solved for: the least-squares Gaussian through one isolated atom's image
(its element's projected potential to :data:`~.adf.ADF_POTENTIAL_POWER`, through the probe) is
as wide as the run's atoms of that element, in the median.  The probe's aberrations (its rings
and tails) stay as assumed; only its spread follows the data.  numpy/scipy.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from gaussian_atoms_method.physics.adf import ADF_POTENTIAL_POWER, adf_kernel_transform
from gaussian_atoms_method.physics.microscope import ProbeOptics, squared_frequencies

GRID_SPACING_A = 0.05
"""The fine grid one atom's image is drawn on, Å: ten times finer than the narrowest atom
(a blurred atom is 0.5 Å wide or more), so the least-squares width is the continuum's to 0.1%."""

GRID_SIZE_PX = 256
"""The fine grid's side, pixels: 12.8 Å, beyond the few Å an aberrated probe's tails reach."""

LARGEST_SOURCE_FWHM_A = 4.0
"""The widest source tried, Å: an atom this blurred is 1.7 Å wide, beyond any atom-like width
(``max_atom_sigma_A`` 1.5)."""


def _fine_grid_r2() -> np.ndarray:
    """(GRID_SIZE_PX, GRID_SIZE_PX) squared distances (Å²) from the fine grid's centre pixel."""
    offsets = (np.arange(GRID_SIZE_PX) - GRID_SIZE_PX // 2) * GRID_SPACING_A
    return offsets[:, None] ** 2 + offsets[None, :] ** 2


def least_squares_width_A(image: np.ndarray) -> float:
    """The width (Å) of the 2D Gaussian, centred on the fine grid's centre pixel, that fits the
    (GRID_SIZE_PX, GRID_SIZE_PX) ``image`` best in least squares, its amplitude free.

    >>> r2 = _fine_grid_r2()
    >>> round(least_squares_width_A(np.exp(-0.5 * r2 / 0.6**2)), 4)
    0.6
    """
    from scipy.optimize import minimize_scalar

    r2 = _fine_grid_r2()

    def unexplained(sigma: float) -> float:  # the residual's power with the best amplitude at sigma
        g = np.exp(-0.5 * r2 / sigma**2)
        return -(float((image * g).sum()) ** 2) / float((g * g).sum())

    return float(minimize_scalar(unexplained, bounds=(0.05, 3.0), method="bounded", options={"xatol": 1e-5}).x)


@functools.lru_cache(maxsize=64)
def fitted_atom_width_A(element: str, optics: ProbeOptics, power: float = ADF_POTENTIAL_POWER) -> float:
    """The width (Å) of the least-squares 2D Gaussian through one isolated ``element`` atom's ADF
    image (its projected potential to ``power``, :func:`~.adf.adf_kernel_transform`) through the
    probe of ``optics``: what a fit of one Gaussian per atom reads on such an atom.

    >>> from gaussian_atoms_method.physics.microscope import DEFAULT_OPTICS
    >>> narrow = fitted_atom_width_A("Pd", dataclasses.replace(DEFAULT_OPTICS, source_fwhm_A=0.0))
    >>> bool(0.2 < narrow < fitted_atom_width_A("Pd", DEFAULT_OPTICS) < 0.8)
    True
    """
    shape = (GRID_SIZE_PX, GRID_SIZE_PX)
    freq = np.sqrt(squared_frequencies(shape, GRID_SPACING_A))
    k, kernel = adf_kernel_transform(element, power=power)
    atom = np.interp(freq, k, kernel, right=0.0)
    return least_squares_width_A(np.fft.fftshift(np.fft.ifft2(atom * optics.transfer(shape, GRID_SPACING_A)).real))


def rendered_atom_width_A(sigma_A: float, kernel_widths_A=(), kernel_weights=()) -> float:
    """The width (Å) of the least-squares 2D Gaussian through one atom as the fit renders it: a
    Gaussian of ``sigma_A`` through its point-spread kernel (``(1 - sum w) delta + sum w_k
    G(s_k)``, :mod:`~.psf`), so that the replica's atom and the fit's are read alike.

    >>> rendered_atom_width_A(0.6)
    0.6
    >>> bool(rendered_atom_width_A(0.6, (1.0, 2.0), (0.1, 0.05)) > 0.6)
    True
    """
    weights = np.asarray(kernel_weights, dtype=np.float64)
    if not weights.any():
        return float(sigma_A)
    r2 = _fine_grid_r2()
    image = (1.0 - weights.sum()) * np.exp(-0.5 * r2 / sigma_A**2) / sigma_A**2
    for s, w in zip(kernel_widths_A, weights):
        total = sigma_A**2 + s**2
        image = image + w * np.exp(-0.5 * r2 / total) / total
    return least_squares_width_A(image)


def probe_as_wide_as(
    element: str, sigma_A: float, optics: ProbeOptics, power: float = ADF_POTENTIAL_POWER
) -> ProbeOptics:
    """``optics`` with the effective source (FWHM, Å) whose ``element`` atom is ``sigma_A`` wide
    (:func:`fitted_atom_width_A`), by bisection between no source and
    :data:`LARGEST_SOURCE_FWHM_A`; where the probe without a source is already wider, no source
    (the replica's atoms are then wider than the views', and its floor errs high).

    >>> from gaussian_atoms_method.physics.microscope import DEFAULT_OPTICS
    >>> wide = fitted_atom_width_A("Pd", DEFAULT_OPTICS)
    >>> round(probe_as_wide_as("Pd", wide, DEFAULT_OPTICS).source_fwhm_A, 2)
    0.7
    """

    def width(fwhm: float) -> float:
        return fitted_atom_width_A(element, dataclasses.replace(optics, source_fwhm_A=round(fwhm, 4)), power)

    low, high = 0.0, LARGEST_SOURCE_FWHM_A
    if not np.isfinite(sigma_A) or width(low) >= sigma_A:
        return dataclasses.replace(optics, source_fwhm_A=0.0)
    if width(high) <= sigma_A:
        return dataclasses.replace(optics, source_fwhm_A=high)
    while high - low > 1e-3:  # the width grows with the source
        middle = 0.5 * (low + high)
        low, high = (middle, high) if width(middle) < sigma_A else (low, middle)
    return dataclasses.replace(optics, source_fwhm_A=round(0.5 * (low + high), 4))
