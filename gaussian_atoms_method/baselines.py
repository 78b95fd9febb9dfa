"""Voxel baselines: filtered back-projection and SART, slice by slice along the tilt axis.

scikit-image's ``iradon`` / ``iradon_sart`` reconstruct each slice perpendicular to the tilt
axis.  Conventions (checked in the tests against our projector): with ``theta = +angle`` the
reconstructed slice ``rec[r, c]`` holds the point at in-plane coordinate ``c`` (detector
direction at zero tilt) and depth ``z = r``, both about index ``L // 2``; scikit-image puts the
rotation axis at detector index ``L // 2``, so each sinogram is padded to an odd length and
shifted (cubic spline) to bring our tilt centre (``centre_px``) there.  Values are returned in
projection units per Å (V for projected potentials in V·Å).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage


@dataclass
class Volume:
    """A reconstructed volume ``data[x, y, z]`` on a regular grid.

    Attributes
    ----------
    data : (X, Y, Z) float array
    spacing_A : float
        Voxel size, Å.
    origin_index : (3,) float array
        Fractional voxel index of the tilt centre (the coordinate origin before ``origin_A``).
    """

    data: np.ndarray
    spacing_A: float
    origin_index: np.ndarray

    def index_to_A(self, index: np.ndarray) -> np.ndarray:
        """(M, 3) fractional voxel indices -> (M, 3) positions in Å about the tilt centre."""
        return (np.asarray(index, dtype=np.float64) - self.origin_index) * self.spacing_A

    def resample(self, shape, voxel_size_A: float) -> np.ndarray:
        """Values on a centred grid of ``shape`` (voxel ``i`` at ``(i - (n - 1) / 2) * voxel_size_A``
        about the tilt centre), by trilinear interpolation; zero outside this volume."""
        axes = [(np.arange(n) - (n - 1) / 2) * voxel_size_A / self.spacing_A + self.origin_index[a] for a, n in enumerate(shape)]
        return ndimage.map_coordinates(self.data, np.meshgrid(*axes, indexing="ij"), order=1, mode="constant")


def _centred_sinograms(projections: np.ndarray, centre_index: float, axis: int) -> tuple[np.ndarray, int]:
    """Sinograms ``(S, L, N)`` for each slice along ``axis`` of the detector (1 rows, 2 cols),
    padded to odd length ``L`` with the tilt centre moved to index ``L // 2``."""
    n_views = projections.shape[0]
    across = projections.shape[3 - axis]  # the detector direction inside a slice
    length = across + 1 if across % 2 == 0 else across
    stack = np.moveaxis(projections, axis, 0)  # (S, N, across) for axis=2 -> (W, N, H)
    sino = np.zeros((stack.shape[0], length, n_views), dtype=np.float64)
    sino[:, :across, :] = np.swapaxes(stack, 1, 2)
    shift = length // 2 - centre_index
    if abs(shift) > 1e-9:
        sino = ndimage.shift(sino, (0, shift, 0), order=3, mode="constant")
    return sino, length


def reconstruct(
    projections: np.ndarray,
    angles_deg: np.ndarray,
    pixel_size_A: float,
    method: str = "sart",
    tilt_axis: str = "y",
    centre_px=None,
    sart_iterations: int = 1,
    filter_name: str = "ramp",
) -> Volume:
    """FBP or SART reconstruction of a single-axis tilt series.

    Parameters
    ----------
    projections : (N, H, W) array
    angles_deg : (N,) array
    pixel_size_A : float
    method : {"fbp", "sart"}
    tilt_axis : {"y", "x"}
    centre_px : (2,) floats, optional
        Detector (row, col) of the tilt centre; default the middle.
    sart_iterations : int
        SART sweeps (each over all angles).
    filter_name : str
        FBP filter (scikit-image names).

    Returns
    -------
    Volume
        ``data[x, y, z]``, voxel size ``pixel_size_A``, values per Å.
    """
    from skimage.transform import iradon, iradon_sart

    projections = np.asarray(projections, dtype=np.float64)
    _, h, w = projections.shape
    ci, cj = ((h - 1) / 2, (w - 1) / 2) if centre_px is None else centre_px
    # Slices are perpendicular to the tilt axis: for "y" each detector column j is one slice
    # whose in-plane detector coordinate runs along the rows (x), and vice versa.
    slice_axis, in_plane_centre, axis_centre = (2, ci, cj) if tilt_axis == "y" else (1, cj, ci)
    sino, length = _centred_sinograms(projections, in_plane_centre, slice_axis)
    theta = np.asarray(angles_deg, dtype=np.float64)
    slices = []
    for s in sino:
        if method == "fbp":
            rec = iradon(s, theta=theta, filter_name=filter_name, circle=False, output_size=length)
        elif method == "sart":
            rec = None
            for _ in range(max(1, sart_iterations)):
                rec = iradon_sart(s, theta=theta, image=rec)
        else:
            raise ValueError(f"method must be 'fbp' or 'sart', got {method!r}")
        slices.append(rec.T)  # -> (in-plane, depth)
    vol = np.stack(slices, axis=0) / pixel_size_A  # (slice, in-plane, depth)
    if tilt_axis == "y":
        data = np.moveaxis(vol, 0, 1)  # (x, y, z)
        origin = np.array([length // 2, axis_centre, length // 2], dtype=np.float64)
    else:
        data = vol  # (x, y, z) with x the slice axis
        origin = np.array([axis_centre, length // 2, length // 2], dtype=np.float64)
    return Volume(np.ascontiguousarray(data), float(pixel_size_A), origin)
