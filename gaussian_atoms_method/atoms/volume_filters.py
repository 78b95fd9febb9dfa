"""Gaussian smoothing, its Laplacian and local maxima of a voxel volume, in torch on the
volume's device.

The start (:mod:`.candidates`) filters a back-projection of the whole field (the 271^3 Au
volume: 20 million voxels) several times; scipy's ``ndimage`` did that on one CPU core and a
GPU run waited for it.  Off the CPU these are the same separable filters as scipy's
``gaussian_filter`` and ``gaussian_laplace`` (the same sampled kernels, ``truncate`` 4, and scipy's default
``reflect`` boundary: the edge sample repeated, ``d c b a | a b c d | d c b a``), so they give
scipy's values to float rounding (tests compare them in float64), on any device.  On the CPU
scipy's own 1-D passes run, over slabs in threads (:mod:`.host_filters`).
"""

from __future__ import annotations

import numpy as np
import torch

from gaussian_atoms_method.atoms import host_filters
from gaussian_atoms_method.physics.noise import gaussian_taps


def off_cpu(volume: torch.Tensor, choice: bool | None) -> bool:
    """``choice``, or by default whether ``volume`` lies off the CPU (where torch's kernels are
    the fast ones)."""
    return volume.device.type != "cpu" if choice is None else choice


def gaussian_kernel1d(sigma: float, order: int = 0, truncate: float = 4.0) -> np.ndarray:
    """scipy's sampled 1D Gaussian (``order`` 0) or its second derivative (``order`` 2), of
    radius ``int(truncate * sigma + 0.5)`` samples, normalised as scipy does (the Gaussian
    sums to one before the derivative's polynomial multiplies it)."""
    if order not in (0, 2):
        raise ValueError(f"order must be 0 or 2, got {order}")
    radius = int(truncate * float(sigma) + 0.5)
    phi = gaussian_taps(sigma, radius)
    if order == 0:
        return phi
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    return phi * (x**2 / sigma**4 - 1.0 / sigma**2)


def _filter_axis(volume: torch.Tensor, kernel: np.ndarray, axis: int) -> torch.Tensor:
    """Correlate ``volume`` with the symmetric, odd-length ``kernel`` along ``axis``, scipy's ``reflect``
    boundary (the edge sample repeated, reflections of reflections where the kernel is longer
    than the axis)."""
    n, radius = volume.shape[axis], len(kernel) // 2
    if radius <= n:
        padded = torch.cat(
            [volume.narrow(axis, 0, radius).flip(axis), volume, volume.narrow(axis, n - radius, radius).flip(axis)],
            axis,
        )
    else:  # a kernel longer than the axis: reflections of reflections
        index = np.mod(np.arange(-radius, n + radius), 2 * n)
        index = np.where(index >= n, 2 * n - 1 - index, index)
        padded = volume.index_select(axis, torch.as_tensor(index, device=volume.device))
    # A weighted sum of shifted copies: on the 2-core CPU 0.3 s an axis of the 271^3 volume in
    # float32, against 0.9 s for conv3d and 3 s for conv1d over its rows (scipy: 0.36 s).
    out = padded.narrow(axis, 0, n) * float(kernel[0])
    for k in range(1, len(kernel)):
        out.add_(padded.narrow(axis, k, n), alpha=float(kernel[k]))
    return out


def _pass(volume: torch.Tensor, sigma_vox: float, axis: int, order: int, in_torch: bool) -> torch.Tensor:
    """One 1-D Gaussian (``order`` 0) or second-derivative (``order`` 2) pass along ``axis``: in
    torch (:func:`_filter_axis`), or scipy's own in threads (:mod:`.host_filters`)."""
    if in_torch:
        return _filter_axis(volume, gaussian_kernel1d(sigma_vox, order), axis)
    return torch.from_numpy(host_filters.gaussian_pass(volume.numpy(), sigma_vox, axis, order))


def gaussian_filter(
    volume: torch.Tensor, sigma_vox: float, in_torch: bool | None = None, axes: tuple[int, ...] | None = None
) -> torch.Tensor:
    """scipy's ``ndimage.gaussian_filter(volume, sigma_vox)`` of a tensor, on its device.

    Parameters
    ----------
    volume : (X, Y, Z) tensor
    sigma_vox : float
        Standard deviation of the Gaussian along every axis, voxels.
    in_torch : bool, optional
        Filter in torch (default: off the CPU).  On the CPU scipy's own 1-D passes run, over
        slabs in threads (:mod:`.host_filters`): scipy's values bit for bit.
    axes : tuple of int, optional
        Filter along these axes only (scipy's sigma 0 along the others); default every axis.
    """
    in_torch = off_cpu(volume, in_torch)
    for axis in range(volume.ndim) if axes is None else axes:
        volume = _pass(volume, sigma_vox, axis, 0, in_torch)
    return volume


def _laplace(volume: torch.Tensor, x: torch.Tensor, xy: torch.Tensor, sigma_vox: float, in_torch: bool) -> torch.Tensor:
    """scipy's ``gaussian_laplace`` from the volume and its smoothings along x and x then y:
    the d2/dx2, d2/dy2, d2/dz2 terms summed in scipy's order."""
    p = lambda v, axis, order: _pass(v, sigma_vox, axis, order, in_torch)  # noqa: E731
    d2z = p(xy, 2, 2)
    d2y = p(p(x, 1, 2), 2, 0)
    out = p(p(p(volume, 0, 2), 1, 0), 2, 0)  # d2/dx2
    out += d2y
    out += d2z
    return out


def gaussian_laplace(volume: torch.Tensor, sigma_vox: float, in_torch: bool | None = None) -> torch.Tensor:
    """scipy's ``ndimage.gaussian_laplace(volume, sigma_vox)`` of a 3D tensor: the sum over
    axes of the Gaussian's second derivative along that axis and the Gaussian along the
    others.  The smoothing along x is shared between two terms (eight 1D passes, not nine).
    ``in_torch``: as :func:`gaussian_filter`."""
    in_torch = off_cpu(volume, in_torch)
    x = _pass(volume, sigma_vox, 0, 0, in_torch)
    return _laplace(volume, x, _pass(x, sigma_vox, 1, 0, in_torch), sigma_vox, in_torch)


def gaussian_filter_and_laplace(
    volume: torch.Tensor, sigma_vox: float, in_torch: bool | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`gaussian_filter` and :func:`gaussian_laplace` of a 3D tensor at one width, the
    smoothings along x and x then y made once for both (nine 1D passes, not twelve)."""
    in_torch = off_cpu(volume, in_torch)
    x = _pass(volume, sigma_vox, 0, 0, in_torch)
    xy = _pass(x, sigma_vox, 1, 0, in_torch)
    return _pass(xy, sigma_vox, 2, 0, in_torch), _laplace(volume, x, xy, sigma_vox, in_torch)


def as_volume(data, device: str | torch.device = "cpu", dtype: torch.dtype | None = torch.float64) -> torch.Tensor:
    """``data`` (an array or tensor) as a contiguous tensor on ``device`` (an array already of
    ``dtype`` on the CPU is shared, not copied); ``dtype`` None keeps the data's."""
    return torch.as_tensor(
        np.ascontiguousarray(data) if isinstance(data, np.ndarray) else data, device=device, dtype=dtype
    ).contiguous()
