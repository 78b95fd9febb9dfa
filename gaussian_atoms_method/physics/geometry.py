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

* ``tilt_axis_angle_deg`` (default 0): the tilt axis may lie at an angle in the image, as
  practitioners' series often do (IMOD and SerialEM report values such as -86 deg).  The
  recorded image is the ideal one (tilt axis along the detector direction ``tilt_axis`` names:
  rows for "x", columns for "y") turned in the detector plane by that angle, counterclockwise
  when the image is shown with its first axis (rows) pointing up, as IMOD shows an MRC stack
  (rows = Y): a point at ideal detector coordinates ``u`` is recorded at ``R u`` with
  ``R = [[cos a, sin a], [-sin a, cos a]]`` on (row, column) coordinates.  In scipy's terms the
  recorded image is ``scipy.ndimage.rotate(ideal, -a, reshape=False)``.  IMOD's angle is
  measured from Y, the rows: it is this angle for ``tilt_axis="x"``, and this angle minus 90
  deg for ``tilt_axis="y"`` (:func:`imod_axis_angle`).

* Euler angles ``(phi, theta, psi)`` (degrees): each view is ``R = Ra(phi) Rb(theta) Rc(psi)``
  (standard right-handed rotations) and the detector is ``R^T`` (:func:`detector_axes_from_euler`).
  GENFIRE writes Z-Y-Z (``convention="zyz"``: its ``vector1..3`` are z, y, z), RESIRE Z-Y-X
  (``"zyx"``: z, y, x); ``phi = psi = 0`` is the tilt ``theta`` about ``y`` in both.

A detector orientation is a 3x3 matrix ``D`` whose rows are the world directions of the
detector row axis, the detector column axis and the beam; ``D @ r`` gives the detector
coordinates (row, column, depth) of a world point ``r``.
"""

from __future__ import annotations

import numpy as np

TILT_AXES = ("x", "y")

EULER_CONVENTIONS = ("zyz", "zyx")
"""The axes of ``(phi, theta, psi)``: Z-Y-Z as GENFIRE writes them, Z-Y-X as RESIRE does."""


def in_plane_rotation(tilt_axis_angle_deg: float) -> np.ndarray:
    """(2, 2) matrix ``R`` taking ideal (row, column) detector coordinates to recorded ones for a
    tilt axis at ``tilt_axis_angle_deg`` in the image (module docstring)."""
    a = np.deg2rad(float(tilt_axis_angle_deg))
    return np.array([[np.cos(a), np.sin(a)], [-np.sin(a), np.cos(a)]])


def imod_axis_angle(imod_angle_deg: float, tilt_axis: str) -> float:
    """Our ``tilt_axis_angle_deg`` for IMOD's tilt-axis angle (counterclockwise from Y, the
    rows): the same for ``tilt_axis="x"`` (rows), 90 deg more for ``"y"`` (columns), in (-180, 180]."""
    angle = float(imod_angle_deg) + (90.0 if tilt_axis == "y" else 0.0)
    return float(-((-angle + 180.0) % 360.0 - 180.0))


def to_nominal_axis(projections: np.ndarray, tilt_axis_angle_deg: float, centre_px=None, order: int = 1) -> np.ndarray:
    """Resample (N, H, W) recorded projections to the ideal detector (tilt axis along the
    nominal direction) about the tilt centre ``centre_px`` (default the middle), by
    interpolation of ``order``; zero outside the recorded image.  For the slice-by-slice
    reconstructions (FBP, SART), which need the axis along rows or columns; the fit itself
    uses the recorded pixels as they are."""
    from scipy import ndimage

    projections = np.asarray(projections)
    if float(tilt_axis_angle_deg) == 0.0:
        return projections
    h, w = projections.shape[1:]
    centre = (
        (np.array([h, w], dtype=np.float64) - 1) / 2 if centre_px is None else np.asarray(centre_px, dtype=np.float64)
    )
    rotation = in_plane_rotation(tilt_axis_angle_deg)
    # ideal pixel u (about the centre) is read from the recorded image at R u.
    offset = centre - rotation @ centre
    return np.stack(
        [ndimage.affine_transform(p, rotation, offset=offset, order=order, mode="constant") for p in projections]
    )


def detector_axes_from_tilts(
    angles_deg: np.ndarray, tilt_axis: str = "y", tilt_axis_angle_deg: float = 0.0
) -> np.ndarray:
    """Detector orientations for single-axis tilts.

    Parameters
    ----------
    angles_deg : (N,) array
        Tilt angles in degrees.
    tilt_axis : {"y", "x"}
        World axis the specimen is tilted about (see module docstring).
    tilt_axis_angle_deg : float
        Angle of the tilt axis in the recorded image (module docstring); the detector's row and
        column directions turn in the detector plane, the beam stays.

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
    if float(tilt_axis_angle_deg) != 0.0:
        # recorded coordinates R (D_ideal r): the recorded axes are R's combinations of the ideal ones.
        rotation = in_plane_rotation(tilt_axis_angle_deg)
        rows, cols = rotation[0, 0] * rows + rotation[0, 1] * cols, rotation[1, 0] * rows + rotation[1, 1] * cols
    return np.stack([rows, cols, beam], axis=1)


def rotation_about(axis: str, angles_deg) -> np.ndarray:
    """(N, 3, 3) right-handed rotations by ``angles_deg`` (N,) about the world ``axis`` ("x",
    "y" or "z"), as GENFIRE's and RESIRE's ``MatrixQuaternionRot``."""
    a = np.deg2rad(np.asarray(angles_deg, dtype=np.float64).reshape(-1))
    c, s = np.cos(a), np.sin(a)
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    r = np.zeros((len(a), 3, 3))
    r[:, 3 - i - j, 3 - i - j] = 1.0
    r[:, i, i], r[:, j, j], r[:, i, j], r[:, j, i] = c, c, -s, s
    return r


def detector_axes_from_euler(euler_deg: np.ndarray, convention: str = "zyz") -> np.ndarray:
    """Detector orientations for Euler angles, as GENFIRE and RESIRE project.

    Both build each view as ``R = Ra(phi) Rb(theta) Rc(psi)`` from right-handed rotations about
    their ``vector1..3`` and sample the volume along ``R^T``'s first two rows (``kx`` along the
    array's rows): ``R^T``'s rows are the detector's row and column directions and the beam.
    GENFIRE's axes are z, y, z (``convention="zyz"``); RESIRE's are z, y, x (``"zyx"``).  At
    ``phi = psi = 0`` both are :func:`detector_axes_from_tilts` about ``y``.

    Parameters
    ----------
    euler_deg : (N, 3) array
        ``(phi, theta, psi)`` per view, degrees.
    convention : {"zyz", "zyx"}

    Returns
    -------
    D : (N, 3, 3) float64 array

    Examples
    --------
    >>> d = detector_axes_from_euler([[0.0, 30.0, 0.0]], "zyx")
    >>> np.allclose(d, detector_axes_from_tilts([30.0]))
    True
    """
    if convention not in EULER_CONVENTIONS:
        raise ValueError(f"euler_convention must be one of {list(EULER_CONVENTIONS)}, got {convention!r}")
    phi, theta, psi = np.asarray(euler_deg, dtype=np.float64).reshape(-1, 3).T
    rotation = rotation_about("z", phi) @ rotation_about("y", theta) @ rotation_about(convention[2], psi)
    return np.ascontiguousarray(np.swapaxes(rotation, 1, 2))


def detector_axes_of(
    angles_deg, tilt_axis: str = "y", tilt_axis_angle_deg: float = 0.0, euler_convention: str = "zyz"
) -> np.ndarray:
    """(N, 3, 3) detector orientations of ``angles_deg``: (N,) tilts about ``tilt_axis``
    (:func:`detector_axes_from_tilts`), or (N, 3) Euler angles in ``euler_convention``, which
    give each view's whole orientation (:func:`detector_axes_from_euler`)."""
    angles = np.asarray(angles_deg, dtype=np.float64)
    if angles.ndim == 2 and angles.shape[1] == 3:
        return detector_axes_from_euler(angles, euler_convention)
    return detector_axes_from_tilts(angles, tilt_axis, tilt_axis_angle_deg)


def pixel_centres(n_pixels: int, pixel_size: float, centre_index: float | None = None) -> np.ndarray:
    """Coordinates of the pixel centres along one detector axis, relative to the tilt axis.

    Returns an ``(n_pixels,)`` array ``(i - centre_index) * pixel_size``; the tilt axis is at
    ``centre_index``, by default the middle ``(n_pixels - 1) / 2``.
    """
    if centre_index is None:
        centre_index = (n_pixels - 1) / 2.0
    return (np.arange(n_pixels, dtype=np.float64) - centre_index) * pixel_size


def project_volume(
    volume: np.ndarray, angle_deg: float, tilt_axis: str = "y", order: int = 1, centre=None
) -> np.ndarray:
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
