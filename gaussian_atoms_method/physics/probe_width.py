"""A replica's probe as wide as the views' atoms: the effective source read from the views.

A run's own replica (:mod:`~gaussian_atoms_method.engine.own_floor`) draws its atoms through a
probe with rings and tails (:data:`~.microscope.DEFAULT_OPTICS`; for phase images its aperture's
transfer, :func:`contrast_transfer`) to learn what a bias alike in every view does to its fit.
The probe is an assumption, but its spread need not be.  A probe wider than the views' atoms makes
bonded neighbours overlap far more than they do, and the replica's refit errs by that overlap,
not by the views' physics (carbon phase images, 1,512 atoms, 10,000 e/Å²: with a fixed 0.7 Å
source the replica's refit erred 14/13/17 pm, five times the fit's own errors).

So the source is read from the views (:func:`source_read_from_views`): the run's atoms drawn with
no source, against the measured views, in their cross-spectrum, where the noise averages out and
a source's Gaussian is what remains.  Where the views hold no correlation with the atoms, the
source whose isolated atom is as wide as the run's atoms (:func:`probe_as_wide_as`; in bonded
carbon the fitted widths also hold the neighbours' tails, and it read 0.90 Å for a 0.7 Å source
where the cross-spectrum read 0.63-0.65 Å).  For ADF views the probe's aberrations are read the
same way, among a few candidate probes (:func:`probe_read_from_views`): drawn with the assumed
rings whatever the views showed, the replica of a particle imaged through a Gaussian probe
overstated its bias, and the run's intervals held 0.98-0.99 of its errors.  numpy/scipy.
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

FWHM_PER_SIGMA = 2.0 * np.sqrt(2.0 * np.log(2.0))
"""A Gaussian's full width at half maximum over its standard deviation."""

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


def contrast_transfer(optics: ProbeOptics, contrast: str = "adf"):
    """``(transfer(shape, spacing_A), power)`` of the views a series' ``contrast`` names: ADF's
    probe intensity and :data:`~.adf.ADF_POTENTIAL_POWER`, or a phase image's aperture transfer
    (:func:`~.phase.ptychographic_transfer`, the source of ``optics``) and the potential itself.

    >>> from gaussian_atoms_method.physics.microscope import DEFAULT_OPTICS
    >>> transfer, power = contrast_transfer(DEFAULT_OPTICS, "phase")
    >>> power, float(transfer((64, 64), 0.1)[0, 25])  # nothing beyond twice the aperture
    (1.0, 0.0)
    """
    from gaussian_atoms_method.physics.phase import ptychographic_transfer

    if contrast == "phase":
        return ptychographic_transfer(optics), 1.0
    if contrast == "adf":
        return optics.transfer, ADF_POTENTIAL_POWER
    raise ValueError(f"contrast must be 'adf' or 'phase', got {contrast!r}")


@functools.lru_cache(maxsize=64)
def fitted_atom_width_A(element: str, optics: ProbeOptics, contrast: str = "adf") -> float:
    """The width (Å) of the least-squares 2D Gaussian through one isolated ``element`` atom's
    image in views of ``contrast`` (:func:`contrast_transfer`: its projected potential to the
    contrast's power, :func:`~.adf.adf_kernel_transform`, through the probe or the aperture of
    ``optics``): what a fit of one Gaussian per atom reads on such an atom.

    >>> from gaussian_atoms_method.physics.microscope import DEFAULT_OPTICS
    >>> narrow = fitted_atom_width_A("Pd", dataclasses.replace(DEFAULT_OPTICS, source_fwhm_A=0.0))
    >>> bool(0.2 < narrow < fitted_atom_width_A("Pd", DEFAULT_OPTICS) < 0.8)
    True
    """
    shape = (GRID_SIZE_PX, GRID_SIZE_PX)
    freq = np.sqrt(squared_frequencies(shape, GRID_SPACING_A))
    transfer, power = contrast_transfer(optics, contrast)
    k, kernel = adf_kernel_transform(element, power=power)
    atom = np.interp(freq, k, kernel, right=0.0)
    return least_squares_width_A(np.fft.fftshift(np.fft.ifft2(atom * transfer(shape, GRID_SPACING_A)).real))


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


def probe_as_wide_as(element: str, sigma_A: float, optics: ProbeOptics, contrast: str = "adf") -> ProbeOptics:
    """``optics`` with the effective source (FWHM, Å) whose ``element`` atom is ``sigma_A`` wide
    in views of ``contrast`` (:func:`fitted_atom_width_A`), by bisection between no source and
    :data:`LARGEST_SOURCE_FWHM_A`; where the probe without a source is already wider, no source
    (the replica's atoms are then wider than the views', and its floor errs high).

    >>> from gaussian_atoms_method.physics.microscope import DEFAULT_OPTICS
    >>> wide = fitted_atom_width_A("Pd", DEFAULT_OPTICS)
    >>> round(probe_as_wide_as("Pd", wide, DEFAULT_OPTICS).source_fwhm_A, 2)
    0.7
    >>> phase = fitted_atom_width_A("C", DEFAULT_OPTICS, "phase")
    >>> round(probe_as_wide_as("C", phase, DEFAULT_OPTICS, "phase").source_fwhm_A, 2)
    0.7
    """

    def width(fwhm: float) -> float:
        return fitted_atom_width_A(element, dataclasses.replace(optics, source_fwhm_A=round(fwhm, 4)), contrast)

    low, high = 0.0, LARGEST_SOURCE_FWHM_A
    if not np.isfinite(sigma_A) or width(low) >= sigma_A:
        return dataclasses.replace(optics, source_fwhm_A=0.0)
    if width(high) <= sigma_A:
        return dataclasses.replace(optics, source_fwhm_A=high)
    while high - low > 1e-3:  # the width grows with the source
        middle = 0.5 * (low + high)
        low, high = (middle, high) if width(middle) < sigma_A else (low, middle)
    return dataclasses.replace(optics, source_fwhm_A=round(0.5 * (low + high), 4))


STRUCTURE_FREQUENCY_PER_A = 0.25
"""The lowest spatial frequency the source is read at, 1/Å: structure finer than 4 Å (atoms and
their spacings), not a view's floor or support, which vary over tens of Å."""


def source_read_from_views(measured: np.ndarray, sharp: np.ndarray, pixel_size_A: float) -> float:
    """The source (FWHM, Å) that turns ``sharp`` (V, H, W), the run's atoms drawn with no source,
    into the ``measured`` views (V, H, W): the cross-spectrum ``Re <M S*>`` over the views,
    in rings of frequency from :data:`STRUCTURE_FREQUENCY_PER_A`, is ``g |S|^2 exp(-2 pi^2
    s^2 k^2)`` (noise is independent of ``S`` and averages out; a source's Gaussian blur
    multiplies the spectrum), solved for ``s`` by least squares, the gain ``g`` in closed form.
    What the fitted atoms miss of the truth (their errors blur like a source) is read with it.
    NaN where the views hold no positive correlation with the atoms.

    >>> rng = np.random.default_rng(0)
    >>> sharp = rng.normal(size=(4, 64, 64))
    >>> from gaussian_atoms_method.physics.microscope import gaussian_transfer
    >>> blur = gaussian_transfer(0.7 / FWHM_PER_SIGMA, (64, 64), 0.2)
    >>> measured = np.fft.ifft2(np.fft.fft2(sharp) * blur).real + rng.normal(0, 0.5, sharp.shape)
    >>> round(source_read_from_views(measured, sharp, 0.2), 1)
    0.7
    """
    spectra = _spectra(measured, sharp)
    return _source_fit(*spectra, np.ones(spectra[0].shape), pixel_size_A)[0]


def probe_read_from_views(
    measured: np.ndarray, plain: np.ndarray, pixel_size_A: float, candidates: tuple[ProbeOptics, ...]
) -> ProbeOptics:
    """Of ``candidates`` (their sources ignored), the probe whose transfer with the source read
    for it (:func:`source_read_from_views`) explains most of the ``measured`` views (V, H, W) in
    the atoms' frequencies: ``plain`` (V, H, W) the run's atoms drawn with no probe (band-limited
    at the detector's Nyquist frequency).  Each candidate's drawing is ``plain`` times its transfer
    (the transfers are round), and with the gain and source at their best its misfit is
    ``|M|^2 - (sum_k Re<M S*> E)^2 / sum_k |S|^2 E^2`` (``E`` the source's transfer): the same
    ``|M|^2`` for every candidate, so the one of least misfit is the best.  Returned with its
    source (NaN where the views hold no correlation with the atoms).

    >>> rng = np.random.default_rng(0)
    >>> plain = rng.normal(size=(4, 64, 64))
    >>> sharp, rings = ProbeOptics(defocus_A=0.0, cs_A=0.0), ProbeOptics(defocus_A=80.0)
    >>> truth = dataclasses.replace(rings, source_fwhm_A=0.8).transfer((64, 64), 0.25).real
    >>> measured = np.fft.ifft2(np.fft.fft2(plain) * truth).real + rng.normal(0, 0.02, plain.shape)
    >>> read = probe_read_from_views(measured, plain, 0.25, (sharp, rings))
    >>> read.defocus_A, round(read.source_fwhm_A, 1)
    (80.0, 0.8)
    """
    spectra = _spectra(measured, plain)
    shape = spectra[0].shape
    best, best_misfit = None, np.inf
    for optics in candidates:
        transfer = dataclasses.replace(optics, source_fwhm_A=0.0).transfer(shape, pixel_size_A).real
        fwhm, misfit = _source_fit(*spectra, transfer, pixel_size_A)
        if misfit < best_misfit:
            best, best_misfit = dataclasses.replace(optics, source_fwhm_A=fwhm), misfit
    return best if best is not None else dataclasses.replace(candidates[0], source_fwhm_A=float("nan"))


def _spectra(measured: np.ndarray, drawn: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) twice: ``Re <M S*>`` and ``|S|^2`` summed over the views."""
    m = np.fft.fft2(np.asarray(measured, np.float64), axes=(1, 2))
    s = np.fft.fft2(np.asarray(drawn, np.float64), axes=(1, 2))
    return (m * s.conj()).real.sum(0), (np.abs(s) ** 2).sum(0)


def _source_fit(cross: np.ndarray, power: np.ndarray, transfer: np.ndarray, pixel_size_A: float):
    """(source FWHM in Å or NaN, misfit less ``|M|^2``) of the drawing ``S T`` (``cross`` and
    ``power`` of ``S``, :func:`_spectra`; ``transfer`` (H, W) real) in rings of frequency from
    :data:`STRUCTURE_FREQUENCY_PER_A`: the source fitted to the rings
    (:func:`source_read_from_views`), the misfit the spectrum's, ``sum |M - g S T E|^2`` at the
    best gain, one source transfer ``E`` a ring."""
    from scipy.optimize import minimize_scalar

    k2 = squared_frequencies(cross.shape, pixel_size_A)
    rings = np.floor(np.sqrt(k2) * min(cross.shape) * pixel_size_A).astype(int)  # one frequency step a ring
    used = np.sqrt(k2) >= STRUCTURE_FREQUENCY_PER_A
    weighted = power * transfer**2
    c, p, k2r = (np.bincount(rings[used], w[used]) for w in (cross * transfer, weighted, k2 * weighted))
    held = p > 0
    c, p, k2r = c[held], p[held], k2r[held] / p[held]
    if c.sum() <= 0:
        return float("nan"), np.inf

    def misfit(sigma: float) -> float:  # the rings' residual with the best gain at sigma
        model = p * np.exp(-2.0 * np.pi**2 * sigma**2 * k2r)
        return -(float((c * model).sum()) ** 2) / float((model * model).sum())

    largest = LARGEST_SOURCE_FWHM_A / FWHM_PER_SIGMA
    sigma = minimize_scalar(misfit, bounds=(0.0, largest), method="bounded", options={"xatol": 1e-4}).x
    source = np.exp(-2.0 * np.pi**2 * sigma**2 * k2r)  # the spectrum's misfit with the best gain
    return float(round(sigma * FWHM_PER_SIGMA, 4)), -(float((c * source).sum()) ** 2) / float((p * source**2).sum())
