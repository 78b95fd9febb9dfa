"""Per-atom position precision from the curvature of the data term (the Cramér-Rao bound).

A fitted atom is an isotropic Gaussian whose projection in every view is a 2D Gaussian of
peak ``A = q sigma sqrt(2 pi)`` centred on ``P_v r`` (``P_v``: the view's 2 x 3 detector
axes).  With independent Gaussian pixel noise of standard deviation ``s``, the curvature of
the least-squares loss about the fitted position, the Fisher information, is::

    F = (1 / s^2) sum_v sum_pixels (dI/dr)(dI/dr)^T
      = (pi A^2 / (2 s^2 p^2)) sum_v P_v^T P_v

(``p``: pixel size; the pixel sum of the squared gradient of a 2D Gaussian is
``pi A^2 / (2 p^2)`` along each detector axis, and the two axes are uncorrelated).  The
covariance of the position is ``F^-1``: its diagonal gives the precision along x, y and z.
Position is decoupled from width and amplitude for a symmetric peak, so fitting those too
does not widen it.  An L1 fit (the paper's loss) is the median-type estimator, whose variance
under Gaussian noise is ``pi / 2`` times the least-squares one.  The missing wedge enters
through ``sum_v P_v^T P_v``: with tilts up to +-70 degrees about y, z is less well fixed than x.

It is a lower bound: overlap with neighbours, the non-Gaussian atom shape (Lobato potentials,
probe blur) and an unconverged fit only add error.  ``docs/results.md`` checks it against the
actual error on simulated data.
"""

from __future__ import annotations

import numpy as np

from gaussian_atoms_method.physics.noise import mad_std

#: Variance of the L1 (median) estimator over the least-squares one under Gaussian noise.
L1_EFFICIENCY_FACTOR = np.pi / 2


def robust_noise_std(residuals: np.ndarray) -> float:
    """Standard deviation of Gaussian noise from residuals, ``1.4826 * MAD`` (robust to the
    few pixels where the model is wrong)."""
    try:
        return mad_std(residuals)
    except ValueError:
        raise ValueError("no finite residuals to estimate the noise from") from None


def position_std_A(
    sigmas_A: np.ndarray,
    amplitudes: np.ndarray,
    detector_axes: np.ndarray,
    pixel_size_A: float,
    noise_std: float,
    loss: str = "l1",
) -> np.ndarray:
    """Standard deviation of each atom's fitted position along world x, y, z.

    Parameters
    ----------
    sigmas_A : (N,) array
        Gaussian widths, Å.
    amplitudes : (N,) array
        3D peaks, projection units per Å (as in :class:`~.atoms.AtomSet`).
    detector_axes : (V, 2, 3) or (V, 3, 3) array
        Per view, the world directions of the detector rows and columns
        (:func:`~.geometry.detector_axes_from_tilts`).
    pixel_size_A : float
    noise_std : float
        Standard deviation of the pixel noise, projection units (e.g. :func:`robust_noise_std`
        of the fit's residuals).
    loss : {"l1", "l2"}
        The data term the positions were fitted with.

    Returns
    -------
    std_A : (N, 3) array, Å
    """
    if loss not in ("l1", "l2"):
        raise ValueError(f"loss must be 'l1' or 'l2', got {loss!r}")
    if not (pixel_size_A > 0 and noise_std >= 0):
        raise ValueError(f"need pixel_size_A > 0 and noise_std >= 0, got {pixel_size_A} and {noise_std}")
    axes = np.asarray(detector_axes, dtype=np.float64)[:, :2, :]
    geometry = np.einsum("vki,vkj->ij", axes, axes)  # sum_v P_v^T P_v, (3, 3)
    if np.linalg.cond(geometry) > 1e12:
        raise ValueError("the views do not fix all three coordinates (one tilt, or all tilts alike)")
    geometry_inv_diag = np.diag(np.linalg.inv(geometry))
    peak_2d = np.asarray(amplitudes, dtype=np.float64) * np.asarray(sigmas_A, dtype=np.float64) * np.sqrt(2 * np.pi)
    with np.errstate(divide="ignore"):
        variance_scale = 2.0 * noise_std**2 * pixel_size_A**2 / (np.pi * peak_2d**2)
    if loss == "l1":
        variance_scale = variance_scale * L1_EFFICIENCY_FACTOR
    return np.sqrt(variance_scale[:, None] * geometry_inv_diag[None, :])


def existence_significance(
    sigmas_A: np.ndarray,
    amplitudes: np.ndarray,
    n_views: int,
    pixel_size_A: float,
    noise_std: float,
    loss: str = "l1",
) -> np.ndarray:
    """Each isolated atom's existence significance: its projected peak over the peak's
    Cramér-Rao standard deviation with its width and position held, in noise standard
    deviations (the views' misfit without it, :mod:`.evidence`'s significance with no
    neighbour to take up its image; neighbours only lower it).

    A peak ``A = q sigma sqrt(2 pi)`` of a 2D Gaussian of width ``sigma`` sums ``A^2 pi sigma^2
    / p^2`` over the pixels of its square, so over ``V`` views of white noise ``s`` the peak is
    known to ``s p / (sigma sqrt(pi V))`` (an L1 fit: times ``sqrt(pi / 2)``).

    Parameters
    ----------
    sigmas_A : (N,) array
        Gaussian widths, Å.
    amplitudes : (N,) array
        3D peaks, projection units per Å (as in :class:`~.atoms.AtomSet`).
    n_views : int
    pixel_size_A : float
    noise_std : float
        Standard deviation of the pixel noise, projection units.
    loss : {"l1", "l2"}

    Returns
    -------
    significance : (N,) array

    >>> existence_significance(np.array([0.5]), np.array([1.0]), 40, 0.5, 0.1, "l2").round(1)
    array([140.5])
    """
    sigmas_A = np.asarray(sigmas_A, dtype=np.float64)
    peak_2d = np.asarray(amplitudes, dtype=np.float64) * sigmas_A * np.sqrt(2 * np.pi)
    efficiency = L1_EFFICIENCY_FACTOR if loss == "l1" else 1.0
    with np.errstate(divide="ignore"):
        return peak_2d * sigmas_A * np.sqrt(np.pi * n_views / efficiency) / (pixel_size_A * noise_std)
