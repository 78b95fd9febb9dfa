"""Tomographic projection of isotropic 3D Gaussians onto an orthographic detector.

Physics: the potential of one atom is modelled as ``q exp(-|r - r_a|^2 / (2 sigma^2))``.  Its
line integral along the beam is exactly a 2D Gaussian of the same ``sigma`` with peak
``q * sigma * sqrt(2 pi)``.  A projection is the plain sum of these (no alpha compositing, no
occlusion, no sorting).  The image value at a pixel is the line integral along the ray through
the pixel centre.

Because an isotropic 2D Gaussian is separable, the image of ``N`` atoms is one matrix product
``G_rows^T diag(peak) G_cols`` of two small matrices of 1D Gaussians, ``(H, N) @ (N, W)``: exact,
differentiable by autograd, and runs on any torch device.  (Keep TF32 off on CUDA: it makes this
product about 0.6% wrong.)
"""

from __future__ import annotations

import math

import torch

SQRT_2PI = math.sqrt(2.0 * math.pi)


def projected_peak(sigmas: torch.Tensor, amplitudes: torch.Tensor) -> torch.Tensor:
    """Peak of the projected 2D Gaussian, ``amplitude * sigma * sqrt(2 pi)``."""
    return amplitudes * sigmas * SQRT_2PI


def gaussian_mass(sigmas: torch.Tensor, amplitudes: torch.Tensor) -> torch.Tensor:
    """Integral of the 3D Gaussian over all space, ``amplitude * (2 pi sigma^2)^(3/2)``."""
    return amplitudes * (2.0 * math.pi * sigmas**2) ** 1.5


def project_gaussians(
    means: torch.Tensor,
    sigmas: torch.Tensor,
    amplitudes: torch.Tensor,
    detector_axes: torch.Tensor,
    row_coords: torch.Tensor,
    col_coords: torch.Tensor,
) -> torch.Tensor:
    """Line-integral projections of isotropic Gaussians.

    All lengths are in one unit (Å, or the normalised units used in training).

    Parameters
    ----------
    means : (N, 3) tensor
        Gaussian centres in world coordinates.
    sigmas : (N,) tensor
        Standard deviations (> 0).
    amplitudes : (N,) tensor
        3D peak values ``q``.
    detector_axes : (V, 3, 3) or (V, 2, 3) tensor
        Per view, the world directions of the detector rows and columns (and beam, unused);
        see :mod:`gaussian_atoms_method.geometry`.
    row_coords : (H,) tensor
        Coordinates of the pixel centres along the detector rows.
    col_coords : (W,) tensor
        Coordinates of the pixel centres along the detector columns.

    Returns
    -------
    images : (V, H, W) tensor
        Line integrals, in units of amplitude x length.
    """
    if means.ndim != 2 or means.shape[-1] != 3:
        raise ValueError(f"means must have shape (N, 3), got {tuple(means.shape)}")
    n = means.shape[0]
    if sigmas.shape != (n,) or amplitudes.shape != (n,):
        raise ValueError(
            f"sigmas and amplitudes must have shape ({n},), got {tuple(sigmas.shape)} and {tuple(amplitudes.shape)}"
        )
    # Detector coordinates of every centre in every view: (V, N).
    u = torch.einsum("vc,nc->vn", detector_axes[:, 0, :], means)
    v = torch.einsum("vc,nc->vn", detector_axes[:, 1, :], means)
    inv_two_var = 0.5 / sigmas**2  # (N,)
    peak = projected_peak(sigmas, amplitudes)  # (N,)
    g_rows = torch.exp(-((row_coords[None, :, None] - u[:, None, :]) ** 2) * inv_two_var)  # (V, H, N)
    g_cols = torch.exp(-((col_coords[None, None, :] - v[:, :, None]) ** 2) * inv_two_var[:, None])  # (V, N, W)
    return torch.bmm(g_rows * peak, g_cols)
