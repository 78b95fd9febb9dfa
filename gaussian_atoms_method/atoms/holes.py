"""Where a missing atom could be: inside the material, at least the hard core from every Gaussian.

A light atom beside heavy ones can be missed for good: its neighbours take up its mass (wider,
heavier) early in the fit, so the residual it leaves is weaker than a lone atom's, under the
level that no noise peak reaches anywhere in the volume.  But an atom can only be where none
is within the hard core, and inside the material; those places fill a few percent of the
volume, so a peak there needs a lower level to be as unlikely by chance
(:func:`~.peaks.random_field_threshold` for that many voxels).  On a 2,000-atom Ni-Pd-Pt
particle through ADF physics the residual's back-projection at its 11 missed Ni atoms reached
2.4-5.4 noise standard deviations against the volume's level 5.5; the places an atom could be
held 6% of the volume (level 4.9), and the peaks there above it were 4, each on a missed atom.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull, QhullError, cKDTree

SAMPLES = 50_000
"""Voxels drawn to count the open places (:func:`open_voxel_count`): the count's relative error
is about ``1 / sqrt(SAMPLES x share)``, 2% where the places hold 6% of the volume, and the level
moves by a hundredth of a standard deviation for it."""


def inside_hull(points_A: np.ndarray, hull_of_A: np.ndarray) -> np.ndarray:
    """(M,) bool: each of ``points_A`` (M, 3) lies inside the convex hull of ``hull_of_A``
    (K, 3) (all False where the hull is flat or there are fewer than four points).

    >>> cube = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    >>> inside_hull(np.array([[0.5, 0.5, 0.5], [1.5, 0.5, 0.5]]), cube).tolist()
    [True, False]
    """
    points = np.asarray(points_A, dtype=np.float64).reshape(-1, 3)
    hull_of = np.asarray(hull_of_A, dtype=np.float64).reshape(-1, 3)
    if len(hull_of) < 4 or len(points) == 0:
        return np.zeros(len(points), bool)
    try:
        hull = ConvexHull(hull_of)
    except QhullError:
        return np.zeros(len(points), bool)
    normals, offsets = hull.equations[:, :3], hull.equations[:, 3]
    inside = np.ones(len(points), bool)
    for start in range(0, len(points), 8192):  # (chunk, facets) at a time
        chunk = points[start : start + 8192]
        inside[start : start + 8192] = np.all(chunk @ normals.T + offsets <= 1e-9, axis=1)
    return inside


def open_places(points_A: np.ndarray, existing_A: np.ndarray, hard_core_A: float) -> np.ndarray:
    """(M,) bool: an atom could be at each of ``points_A`` (M, 3): inside the convex hull of the
    Gaussians ``existing_A`` (K, 3) and at least ``hard_core_A`` from every one of them.

    >>> cube = 3.0 * np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    >>> open_places(np.array([[1.5, 1.5, 1.5], [0.5, 0.5, 0.5], [5.0, 1.5, 1.5]]), cube, 2.0).tolist()
    [True, False, False]
    """
    points = np.asarray(points_A, dtype=np.float64).reshape(-1, 3)
    existing = np.asarray(existing_A, dtype=np.float64).reshape(-1, 3)
    if len(existing) < 4 or len(points) == 0:
        return np.zeros(len(points), bool)
    clear = cKDTree(existing).query(points)[0] >= hard_core_A
    clear[clear] = inside_hull(points[clear], existing)
    return clear


def open_voxel_count(
    shape, index_to_A, existing_A: np.ndarray, hard_core_A: float, samples: int = SAMPLES, seed: int = 0
) -> int:
    """How many voxels of a volume of ``shape`` (``index_to_A``: voxel indices (M, 3) -> Å, the
    frame of ``existing_A``) are places an atom could be (:func:`open_places`), counted on
    ``samples`` voxels drawn with ``seed`` (the same volume gives the same count)."""
    shape = np.asarray(shape, dtype=np.int64)
    total = int(np.prod(shape))
    if total == 0 or len(existing_A) < 4:
        return 0
    rng = np.random.default_rng(seed)
    drawn = rng.integers(0, shape, size=(min(samples, total), 3))
    share = float(np.mean(open_places(index_to_A(drawn), existing_A, hard_core_A)))
    return int(round(share * total))
