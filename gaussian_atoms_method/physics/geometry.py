"""Tilt geometry: how a tilt angle turns into a detector orientation.

The convention (also written down in README.md)
-----------------------------------------------
* A projection stack is an array ``(N, H, W)``: tilt index, detector row, detector column.
* World coordinates ``(x, y, z)`` in Å.  At zero tilt the detector rows run along ``x``, the
  columns along ``y`` and the beam along ``z``; a volume array is indexed ``vol[x, y, z]`` and
  its zero-tilt projection is ``vol.sum(axis=2)``.
* The origin is the tilt (rotation) centre.  It projects onto the detector point
  ``centre_px = (ci, cj)`` (in pixel indices), by default the middle of the detector,
  ``((H - 1) / 2, (W - 1) / 2)``: pixel ``(i, j)`` sits at row coordinate ``(i - ci) * pixel_size``
  and column coordinate ``(j - cj) * pixel_size``.  FFT-based packages (RESIRE, GENFIRE) rotate
  about pixel ``n // 2`` instead, half a pixel off for even sizes; their tilt series say so with
  ``centre_px``.
* ``tilt_axis="y"`` (the default) tilts about the ``y`` axis (along the detector columns); a
  positive angle theta projects ``x cos(theta) - z sin(theta)`` onto the detector rows.  This is
  ``scipy.ndimage.rotate(vol, +theta, axes=(0, 2), reshape=False).sum(axis=2)``, the RESIRE /
  GENFIRE convention (checked against the RESIRE sample data in the tests).
  ``tilt_axis="x"`` is the same with the roles of x and y exchanged:
  ``scipy.ndimage.rotate(vol, +theta, axes=(1, 2), reshape=False).sum(axis=2)``.

A detector orientation is a 3x3 matrix ``D`` whose rows are the world directions of the
detector row axis, the detector column axis and the beam; ``D @ r`` gives the detector
coordinates (row, column, depth) of a world point ``r``.
"""

from __future__ import annotations

import numpy as np

TILT_AXES = ("x", "y")


def detector_axes_from_tilts(angles_deg: np.ndarray, tilt_axis: str = "y") -> np.ndarray:
    """Detector orientations for single-axis tilts.

    Parameters
    ----------
    angles_deg : (N,) array
        Tilt angles in degrees.
    tilt_axis : {"y", "x"}
        World axis the specimen is tilted about (see module docstring).

    Returns
    -------
    D : (N, 3, 3) float64 array
        Rows: world direction of the detector rows, of the detector columns, of the beam.
    """
    if tilt_axis not in TILT_AXES:
        raise ValueError(f"tilt_axis must be one of {TILT_AXES}, got {tilt_axis!r}")
    theta = np.deg2rad(np.asarray(angles_deg, dtype=np.float64).reshape(-1))
    c, s = np.cos(theta), np.sin(theta)
    zero, one = np.zeros_like(theta), np.ones_like(theta)
    if tilt_axis == "y":
        rows = np.stack([c, zero, -s], axis=-1)
        cols = np.stack([zero, one, zero], axis=-1)
    else:
        rows = np.stack([one, zero, zero], axis=-1)
        cols = np.stack([zero, c, -s], axis=-1)
    beam = np.cross(rows, cols)
    return np.stack([rows, cols, beam], axis=1)


def pixel_centres(n_pixels: int, pixel_size: float, centre_index: float | None = None) -> np.ndarray:
    """Coordinates of the pixel centres along one detector axis, relative to the tilt axis.

    Returns an ``(n_pixels,)`` array ``(i - centre_index) * pixel_size``; the tilt axis is at
    ``centre_index``, by default the middle ``(n_pixels - 1) / 2``.
    """
    if centre_index is None:
        centre_index = (n_pixels - 1) / 2.0
    return (np.arange(n_pixels, dtype=np.float64) - centre_index) * pixel_size


def project_volume(volume: np.ndarray, angle_deg: float, tilt_axis: str = "y", order: int = 1, centre=None) -> np.ndarray:
    """Project a voxel volume at one tilt: rotate with scipy, then sum along the beam.

    An independent path to the Gaussian projector (interpolation instead of analytic
    integrals), used to pin down the convention.

    Parameters
    ----------
    volume : (X, Y, Z) array
        Voxel values, indexed ``vol[x, y, z]``, voxel size equal to the pixel size.
    angle_deg : float
        Tilt angle in degrees.
    tilt_axis : {"y", "x"}
    order : int
        Spline order of the rotation.
    centre : float or (3,) floats, optional
        Voxel index of the rotation centre; by default the middle ``(n - 1) / 2`` of each axis,
        which is what ``scipy.ndimage.rotate(volume, angle_deg, axes, reshape=False)`` does.

    Returns
    -------
    (X, Y) array: the line integrals in units of value x voxel length.
    """
    from scipy import ndimage

    if tilt_axis not in TILT_AXES:
        raise ValueError(f"tilt_axis must be one of {TILT_AXES}, got {tilt_axis!r}")
    volume = np.asarray(volume)
    if centre is None:
        centre = (np.array(volume.shape, dtype=np.float64) - 1) / 2.0
    centre = np.broadcast_to(np.asarray(centre, dtype=np.float64), (3,))
    a, b = (0, 2) if tilt_axis == "y" else (1, 2)
    theta = np.deg2rad(angle_deg)
    # Output voxel o samples the input at M (o - centre) + centre, as scipy.ndimage.rotate.
    m = np.eye(3)
    m[a, a], m[a, b], m[b, a], m[b, b] = np.cos(theta), np.sin(theta), -np.sin(theta), np.cos(theta)
    rotated = ndimage.affine_transform(volume, m, offset=centre - m @ centre, order=order, mode="constant")
    return rotated.sum(axis=2)
