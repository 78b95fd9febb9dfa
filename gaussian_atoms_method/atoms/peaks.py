"""Peaks in a voxel volume: local maxima, and keeping the strongest of those closer than a
distance.  Shared by the start from a back-projection (:mod:`.initialise`) and the baselines'
atom tracing (:mod:`gaussian_atoms_method.harness.tracing`)."""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree


def local_maxima(volume: np.ndarray) -> np.ndarray:
    """(M, 3) integer indices of the voxels that are maxima of their 3x3x3 neighbourhood (and > 0),
    excluding the border voxels (no neighbours for the sub-voxel fit)."""
    peaks = (volume == ndimage.maximum_filter(volume, size=3, mode="nearest")) & (volume > 0)
    peaks[[0, -1], :, :] = peaks[:, [0, -1], :] = peaks[:, :, [0, -1]] = False
    return np.argwhere(peaks)


def suppress_within(positions: np.ndarray, order: np.ndarray, min_distance: float) -> np.ndarray:
    """Indices kept when visiting ``positions`` in ``order`` and dropping any point within
    ``min_distance`` (inclusive) of one already kept."""
    tree = cKDTree(positions)
    neighbours = tree.query_ball_point(positions, min_distance)
    suppressed = np.zeros(len(positions), dtype=bool)
    kept = []
    for i in order:
        if suppressed[i]:
            continue
        kept.append(i)
        suppressed[neighbours[i]] = True
    return np.asarray(kept, dtype=np.int64)
