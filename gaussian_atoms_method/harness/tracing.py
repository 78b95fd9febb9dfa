"""Atom tracing in a voxel volume, as the paper did for its baselines.

1. Candidates: local maxima of the volume (3x3x3 neighbourhood).
2. Intensity threshold chosen on the data: Otsu's threshold of the candidates' peak values
   (noise maxima and atom maxima form two populations), optionally scaled.
3. Minimum distance: candidates taken in order of intensity, each kept only if it lies more
   than ``min_distance_A`` (2.0 Å) from every atom already kept.
4. Sub-voxel refinement: a parabola through the logarithm of each peak and its two neighbours
   along each axis (exact for a Gaussian peak; a plain parabola where a value is not
   positive), so baselines are not handicapped by the grid (rounding alone costs about 12 pm
   RMSD at 0.25 Å voxels).
"""

from __future__ import annotations

import numpy as np
import torch

from gaussian_atoms_method.atoms import maxima, volume_filters
from gaussian_atoms_method.atoms.maxima import suppress_within_host
from gaussian_atoms_method.atoms.peaks import parabola_vertex


def otsu_threshold(values: np.ndarray) -> float:
    """Otsu's threshold of a 1D sample (scikit-image)."""
    from skimage.filters import threshold_otsu

    values = np.asarray(values, dtype=np.float64)
    if len(values) < 2 or np.ptp(values) == 0:
        return float(values.min()) if len(values) else 0.0
    return float(threshold_otsu(values))


def subvoxel_refine(volume, peaks: np.ndarray) -> np.ndarray:
    """(M, 3) fractional indices: per axis, the vertex of a parabola through the logarithms of
    each peak and its two neighbours (exact for Gaussian peaks), or through the values
    themselves where one of them is not positive.  ``volume``: an array or a tensor (read on
    its device, only the 7 values around each peak copied back)."""
    field = volume if isinstance(volume, torch.Tensor) else volume_filters.as_volume(volume)
    peaks = np.asarray(peaks, dtype=np.int64)
    out = peaks.astype(np.float64)
    f0 = maxima.values_at(field, peaks)
    for axis in range(3):
        step = np.zeros(3, dtype=np.int64)
        step[axis] = 1
        fm = maxima.values_at(field, peaks - step)
        fp = maxima.values_at(field, peaks + step)
        positive = (fm > 0) & (fp > 0) & (f0 > 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            lm, l0, lp = (
                np.log(np.where(positive, fm, 1)),
                np.log(np.where(positive, f0, 1)),
                np.log(np.where(positive, fp, 1)),
            )
        out[:, axis] += parabola_vertex(
            np.where(positive, lm, fm), np.where(positive, l0, f0), np.where(positive, lp, fp)
        )
    return out


def trace_atoms(
    volume, spacing_A: float, min_distance_A: float = 2.0, threshold_scale: float = 1.0, threshold: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Trace atoms in a volume.

    Parameters
    ----------
    volume : (X, Y, Z) array, or tensor (traced on its device: a GPU's SIRT volume stays there)
    spacing_A : float
        Voxel size, Å.
    min_distance_A : float
        Kept atoms are more than this far apart, Å.
    threshold_scale : float
        Multiplies the Otsu threshold of the peak values.
    threshold : float, optional
        An explicit intensity threshold instead of Otsu's.

    Returns
    -------
    indices : (M, 3) float array of fractional voxel indices of the atoms
    intensities : (M,) peak values
    """
    field = volume if isinstance(volume, torch.Tensor) else volume_filters.as_volume(volume)
    peaks = maxima.local_maxima_device(field)
    if len(peaks) == 0:
        return np.zeros((0, 3)), np.zeros(0)
    values = maxima.values_at(field, peaks)
    thr = threshold if threshold is not None else threshold_scale * otsu_threshold(values)
    strong = values >= thr
    peaks, values = peaks[strong], values[strong]
    order = np.argsort(-values, kind="stable")
    keep = suppress_within_host(peaks * spacing_A, order, min_distance_A)
    return subvoxel_refine(field, peaks[keep]), values[keep]
