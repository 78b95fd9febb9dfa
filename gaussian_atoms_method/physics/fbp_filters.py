"""scikit-image's ``iradon`` filtering of projections, as its Fourier filter and as one matrix.

:func:`fourier_filter_of` is scikit-image's filter without importing ``skimage.transform``;
:func:`filter_matrix` is the same zero-padded FFT filtering as a product, a GPU's way (no cuFFT,
whose first use in a process costs a GPU run a quarter of a second or more).
"""

from __future__ import annotations

import numpy as np


def fourier_filter_of(size: int, filter_name: str | None) -> np.ndarray:
    """(size,) scikit-image's ``iradon`` filter in Fourier space (its ``_get_fourier_filter``,
    the same values to the bit, ``tests/test_baselines_and_tracing.py``), here so a start does
    not import ``skimage.transform``: the ramp from the spatial Ram-Lak kernel (Kak & Slaney,
    eq. 61), times the named window."""
    import scipy.fft  # scikit-image's FFT, so its values to the bit

    n = np.concatenate((np.arange(1, size / 2 + 1, 2, dtype=int), np.arange(size / 2 - 1, 0, -2, dtype=int)))
    f = np.zeros(size)
    f[0] = 0.25
    f[1::2] = -1 / (np.pi * n) ** 2
    fourier_filter = 2 * np.real(scipy.fft.fft(f))
    if filter_name == "shepp-logan":
        omega = np.pi * np.fft.fftfreq(size)[1:]
        fourier_filter[1:] *= np.sin(omega) / omega
    elif filter_name == "cosine":
        fourier_filter *= np.fft.fftshift(np.sin(np.linspace(0, np.pi, size, endpoint=False)))
    elif filter_name == "hamming":
        fourier_filter *= np.fft.fftshift(np.hamming(size))
    elif filter_name == "hann":
        fourier_filter *= np.fft.fftshift(np.hanning(size))
    elif filter_name is None:
        fourier_filter[:] = 1
    elif filter_name != "ramp":
        raise ValueError(f"filter_name must be ramp, shepp-logan, cosine, hamming, hann or None, got {filter_name!r}")
    return fourier_filter


def even_filter(length: int, filter_name: str | None) -> tuple[int, np.ndarray]:
    """The FFT length iradon pads an L-sample projection to, and the even part ``E`` of its
    filter over the first ``padded // 2 + 1`` frequencies: iradon takes the real part of
    ``ifft(fft(p) H)``, which for a real ``p`` is ``irfft(rfft(p) E)`` (scikit-image's Hann
    window is not quite even), half the spectrum."""
    padded = max(64, int(2 ** np.ceil(np.log2(2 * length))))
    fourier_filter = fourier_filter_of(padded, filter_name)
    return padded, 0.5 * (fourier_filter + np.roll(fourier_filter[::-1], 1))[: padded // 2 + 1]


def filter_matrix(even_filter: np.ndarray, padded: int, length: int, n_angles: int) -> np.ndarray:
    """(L, L) float64 matrix ``F`` with ``p @ F`` the filtering of
    :func:`~gaussian_atoms_method.physics.reconstruction.filtered_backprojection` of a projection
    ``p`` (L,): ``irfft(rfft(p, padded) E)[:L]`` times iradon's scale ``pi / (2 N)``.  A
    zero-padded circular convolution with the filter's kernel ``k = irfft(E)``, so
    ``F[m, n] = k[(n - m) mod padded]`` (symmetric: ``E`` is real and even); equal to the FFT's
    filtering to float64 rounding (``tests/test_baselines_and_tracing.py``)."""
    kernel = np.fft.irfft(even_filter, n=padded) * (np.pi / (2 * n_angles))
    offsets = np.arange(length)
    return kernel[(offsets[None, :] - offsets[:, None]) % padded]
