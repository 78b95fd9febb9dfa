"""Volume metrics: sampling Gaussians on a voxel grid, and the SSIM of a reconstructed potential.

The atom scores (matching within 0.75 Å, TPR, false positives, RMSD) are in
:mod:`gaussian_atoms_method.atoms.matching`.
"""

from __future__ import annotations

import numpy as np


def voxelise_gaussians(
    positions_A: np.ndarray,
    sigmas_A: np.ndarray,
    amplitudes: np.ndarray,
    voxel_size_A: float,
    shape: tuple[int, int, int],
    origin_index=None,
    radius_sigmas: float = 4.0,
) -> np.ndarray:
    """Sample a sum of isotropic Gaussians on a voxel grid.

    Parameters
    ----------
    positions_A : (M, 3) Å about the grid's origin
    sigmas_A : (M,) Å; amplitudes : (M,) 3D peak values
    voxel_size_A : float
    shape : (X, Y, Z)
    origin_index : (3,) fractional voxel index of position 0; default the middle ``(n - 1) / 2``
    radius_sigmas : float
        Each Gaussian is evaluated within this many sigmas of its centre (4: 3e-4 of its peak).

    Returns
    -------
    (X, Y, Z) float64 array: the Gaussians evaluated at the voxel centres.
    """
    import torch

    shape = tuple(int(s) for s in shape)
    origin = (
        (np.array(shape, dtype=np.float64) - 1) / 2
        if origin_index is None
        else np.asarray(origin_index, dtype=np.float64)
    )
    centres = np.asarray(positions_A, dtype=np.float64) / voxel_size_A + origin  # fractional indices
    sig = np.asarray(sigmas_A, dtype=np.float64) / voxel_size_A
    amp = np.asarray(amplitudes, dtype=np.float64)
    out = torch.zeros(int(np.prod(shape)), dtype=torch.float64)
    strides = torch.tensor([shape[1] * shape[2], shape[2], 1])
    # Widths can differ by orders of magnitude (a stray wide Gaussian): visit atoms from narrow
    # to wide, each chunk with the window of its widest member, sized to ~2e7 voxel values.
    order = np.argsort(sig)
    start = 0
    while start < len(order):
        half = min(int(np.ceil(radius_sigmas * sig[order[start]])), max(shape))
        m = max(1, int(2e7 // (2 * half + 1) ** 3))
        chunk = order[start : start + m]
        half = min(int(np.ceil(radius_sigmas * sig[chunk].max())), max(shape))
        chunk = chunk[: max(1, int(2e7 // (2 * half + 1) ** 3))]
        start += len(chunk)
        offsets = torch.arange(-half, half + 1)
        c = torch.from_numpy(centres[chunk])
        s = torch.from_numpy(sig[chunk])[:, None]
        base = torch.round(c).long()
        idx = base[:, :, None] + offsets  # (m, 3, w)
        g = torch.exp(-((idx - c[:, :, None]) ** 2) / (2 * s[:, :, None] ** 2))  # separable factors
        valid = [(idx[:, a] >= 0) & (idx[:, a] < shape[a]) for a in range(3)]
        g = [torch.where(valid[a], g[:, a], 0.0) for a in range(3)]
        vals = (
            torch.from_numpy(amp[chunk])[:, None, None, None]
            * g[0][:, :, None, None]
            * g[1][:, None, :, None]
            * g[2][:, None, None, :]
        )
        flat = (
            idx[:, 0].clamp(0, shape[0] - 1)[:, :, None, None] * strides[0]
            + idx[:, 1].clamp(0, shape[1] - 1)[:, None, :, None] * strides[1]
            + idx[:, 2].clamp(0, shape[2] - 1)[:, None, None, :] * strides[2]
        )
        out.index_add_(0, flat.reshape(-1), vals.reshape(-1))
    return out.reshape(shape).numpy()


def volume_ssim(volume: np.ndarray, reference: np.ndarray) -> dict:
    """SSIM of a volume against a reference on the same grid (scikit-image).

    The data range is the reference's (max - min); both are reported with the value because
    SSIM swings with them (a mostly-vacuum box scores high for any method).
    """
    from skimage.metrics import structural_similarity

    if volume.shape != reference.shape:
        raise ValueError(f"volume shape {volume.shape} differs from the reference's {reference.shape}")
    data_range = float(reference.max() - reference.min())
    value = structural_similarity(
        np.asarray(volume, np.float64), np.asarray(reference, np.float64), data_range=data_range
    )
    return {
        "ssim": float(value),
        "ssim_data_range": data_range,
        "ssim_reference": "true potential blurred like the data",
    }
