"""Noise as filtered views hold it: a field that shows one variance to neighbouring pixels and a
given multiple of it over an atom.

A run reads its views' noise twice: from neighbouring pixels (Immerkaer's second differences,
:func:`~gaussian_atoms_method.physics.noise.noise_from_projections`) and over an atom (whitened
by the first reading, filtered by the atom's Gaussian;
:func:`~gaussian_atoms_method.physics.view_disagreement.view_disagreement` after a fit).  For
white noise the two agree, and the factor between them is 1; views that were interpolated,
filtered or denoised hold their noise at low frequencies, where an atom sees it and the pixels'
second differences do not, and the factor the run prints is larger (thousands on the measured Ta
film's sub-areas).  A replica whose noise should look like the views' draws a field with both
readings: white noise blurred by a Gaussian of width ``b``, scaled so that neighbouring pixels read
the variance asked for.  The factor grows with ``b`` from 1 at ``b = 0``, so one width gives the
factor asked for (:func:`blur_for_factor`).  One Gaussian blur is the simplest family that holds
both readings; a denoiser's transfer need not be Gaussian, which is why the replica is checked by
reading it again, not by its construction.
"""

from __future__ import annotations

import numpy as np

from gaussian_atoms_method.physics.noise import IMMERKAER_KERNEL, gaussian_taps, noise_from_projections

TRUNCATE = 4.0
"""Gaussian kernels reach this many widths (scipy's ``gaussian_filter`` default, which draws the
field)."""


def _kernel(sigma_px: float) -> np.ndarray:
    """The 2D sampled Gaussian ``gaussian_filter`` applies for ``sigma_px`` (summing to one); the
    identity at zero width."""
    if sigma_px <= 0:
        return np.ones((1, 1))
    taps = gaussian_taps(sigma_px, int(TRUNCATE * sigma_px + 0.5))
    return np.outer(taps, taps)


def _convolve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The full 2D convolution of two small kernels."""
    shape = (a.shape[0] + b.shape[0] - 1, a.shape[1] + b.shape[1] - 1)
    return np.fft.irfft2(np.fft.rfft2(a, shape) * np.fft.rfft2(b, shape), shape)


def readings(blur_px: float, sigma_px: float) -> tuple[float, float]:
    """What the two readings see of unit white noise blurred by ``blur_px`` (pixels): the variance
    neighbouring pixels show (Immerkaer's filter over its 36) and the variance over an atom of
    width ``sigma_px`` in units of what unit white noise leaves there; exact sums over the
    kernels.

    >>> [round(x, 6) for x in readings(0.0, 1.7)]
    [1.0, 1.0]
    """
    blur = _kernel(blur_px)
    atom = _kernel(sigma_px)
    pixel = float((_convolve(IMMERKAER_KERNEL, blur) ** 2).sum()) / 36.0
    over_atom = float((_convolve(atom, blur) ** 2).sum() / (atom**2).sum())
    return pixel, over_atom


def factor_of(blur_px: float, sigma_px: float) -> float:
    """The factor over an atom of width ``sigma_px`` (pixels) that noise blurred by ``blur_px``
    shows against its neighbouring pixels' reading (1 for white noise)."""
    pixel, over_atom = readings(blur_px, sigma_px)
    return over_atom / pixel


def blur_for_factor(factor: float, sigma_px: float) -> float:
    """The Gaussian blur, pixels, that gives noise the ``factor`` over an atom of width
    ``sigma_px`` (pixels) against its neighbouring pixels (0 for a factor of 1 or less: white).
    Found by bisection to 1e-5 of the width; the factor rises monotonically with the blur.

    >>> b = blur_for_factor(100.0, 1.7)
    >>> round(b, 2), round(factor_of(b, 1.7), 1)
    (0.73, 100.0)
    """
    if factor <= 1.0:
        return 0.0
    low, high = 0.0, max(sigma_px, 0.5)
    while factor_of(high, sigma_px) < factor:
        low, high = high, 2.0 * high
        if high > 1e3 * max(sigma_px, 1.0):
            raise ValueError(f"no Gaussian blur gives a factor of {factor:g} over an atom of {sigma_px:g} px")
    while high - low > 1e-5 * high:
        middle = 0.5 * (low + high)
        low, high = (middle, high) if factor_of(middle, sigma_px) < factor else (low, middle)
    return 0.5 * (low + high)


def correlated_noise(shape: tuple[int, ...], factor: float, sigma_px: float, rng: np.random.Generator) -> np.ndarray:
    """A (..., H, W) field of Gaussian noise whose neighbouring pixels read a variance of 1 and which
    shows ``factor`` times that over an atom of width ``sigma_px`` (pixels): white noise blurred by
    :func:`blur_for_factor`'s width, periodic in each image, divided by its pixels' reading.  Scale
    it by the square root of a pixel's variance to draw the views' noise.

    >>> from gaussian_atoms_method.physics.noise import noise_from_projections
    >>> field = correlated_noise((24, 64, 64), 100.0, 1.7, np.random.default_rng(0))
    >>> round(noise_from_projections(field).read_var, 1)
    1.0
    """
    from scipy import ndimage

    blur = blur_for_factor(factor, sigma_px)
    white = rng.standard_normal(shape)
    if blur == 0.0:
        return white
    sigmas = (0,) * (len(shape) - 2) + (blur, blur)
    blurred = ndimage.gaussian_filter(white, sigmas, mode="wrap", truncate=TRUNCATE)
    return blurred / np.sqrt(readings(blur, sigma_px)[0])


def noise_shaped_like(residual: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A (V, H, W) field of Gaussian noise with the power spectrum the ``residual`` (V, H, W)
    shows on average over its views, scaled so that neighbouring pixels read a variance of 1
    (:func:`~.noise.noise_from_projections`), as :func:`correlated_noise` is.  For views whose
    noise has a shape of its own that a fit's residual shows (a phase image's, band-limited by the
    aperture as its signal is), where a blur's shape would put noise at frequencies the views do
    not hold: on 1,512 carbon atoms in phase images at 10,000 e/Å² a replica drawn with
    :func:`correlated_noise` erred 5.8 / 5.4 / 6.8 pm, one drawn with this 4.6 / 4.3 / 5.3 pm, the
    fit on the views themselves 4.0 pm per axis.

    >>> rng = np.random.default_rng(0)
    >>> band = np.fft.ifft2(np.fft.fft2(rng.standard_normal((8, 64, 64))) * (np.hypot(*np.meshgrid(
    ...     np.fft.fftfreq(64), np.fft.fftfreq(64))) < 0.2)).real
    >>> field = noise_shaped_like(band, rng)
    >>> power = (np.abs(np.fft.fft2(field)) ** 2).mean(0)
    >>> bool(power[0, 20:44].max() < 1e-20 * power.max())  # nothing where the residual holds none
    True
    """
    centred = residual - residual.mean(axis=(-2, -1), keepdims=True)
    power = (np.abs(np.fft.fft2(centred, axes=(-2, -1))) ** 2).mean(axis=0)
    white = np.fft.fft2(rng.standard_normal(residual.shape), axes=(-2, -1))
    shaped = np.fft.ifft2(white * np.sqrt(power / max(power.mean(), 1e-300)), axes=(-2, -1)).real
    return shaped / np.sqrt(noise_from_projections(shaped).read_var)
