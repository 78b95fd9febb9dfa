"""Readers for the file formats tilt series come in.

Projection stacks: ``.npy``/``.npz``; ``.tif``/``.tiff`` stacks (tifffile); ``.mrc``/``.st``/
``.ali`` (mrcfile, pixel size from the header when set); ``.emd``/``.h5``/``.hdf5`` (h5py; the
tomviz/Berkeley EMD layout ``data/<name>/data`` with ``dim1..3`` giving the tilt angles);
``.mat`` MATLAB v5 (scipy) and v7.3 (h5py, axes reversed as MATLAB stores them column-major).
Angle files: text (``.txt``, IMOD ``.tlt``/``.rawtlt``, ``.csv``), ``.npy``, ``.mat``.

Each reader returns what it found as a :class:`StackData`; errors are :class:`TiltSeriesError`
with a one-line message naming the file, the variable or dataset, and what was expected.
No nerfstudio import.
"""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import TiltSeriesError

STACK_SUFFIXES = (".npy", ".npz", ".tif", ".tiff", ".mrc", ".st", ".ali", ".emd", ".h5", ".hdf5", ".mat")
ANGLE_SUFFIXES = (".txt", ".tlt", ".rawtlt", ".csv", ".dat", ".npy", ".mat")


@dataclass
class StackData:
    """A projection stack as read: ``(N, H, W)`` after moving the tilt axis first."""

    projections: np.ndarray
    pixel_size_A: float | None = None
    angles_deg: np.ndarray | None = None
    imod_tilt_axis_angle_deg: float | None = None
    """The tilt-axis angle IMOD records in an MRC header's labels ("Tilt axis angle = -86.0"),
    counterclockwise from Y (the rows)."""


def _pick(names: list[str], wanted: str | None, path: Path, what: str) -> str:
    if wanted is not None:
        if wanted not in names:
            raise TiltSeriesError(f"{path}: no {what} {wanted!r}; it holds {sorted(names)}")
        return wanted
    if len(names) != 1:
        raise TiltSeriesError(f"{path}: holds {len(names)} {what}s {sorted(names)}; name the one to use")
    return names[0]


def _tilt_first(array: np.ndarray, tilt_index_axis: int | None, path: Path, name: str) -> np.ndarray:
    if array.ndim != 3:
        raise TiltSeriesError(f"{path}: {name} must be a 3D stack, got shape {array.shape}")
    if tilt_index_axis is not None:
        if not -3 <= tilt_index_axis < 3:
            raise TiltSeriesError(f"{path}: tilt_index_axis must be 0, 1 or 2, got {tilt_index_axis}")
        array = np.moveaxis(array, tilt_index_axis, 0)
    return np.asarray(array)


def read_stack(path: str | Path, dataset: str | None = None, tilt_index_axis: int | None = None) -> StackData:
    """Read a projection stack.

    Parameters
    ----------
    path : file of one of :data:`STACK_SUFFIXES`
    dataset : str, optional
        The variable (.mat, .npz) or HDF5 dataset / EMD group to use when there are several.
    tilt_index_axis : int, optional
        The array axis that indexes the tilts, moved first.  Default: the format's convention
        (first for numpy, TIFF, MRC and HDF5 in C order; the last for MATLAB files, whose
        stacks are stored (H, W, N); the EMD's angle dimension where it says so).
    """
    path = Path(path)
    if not path.is_file():
        raise TiltSeriesError(f"{path}: projections file not found")
    suffix = path.suffix.lower()
    try:
        if suffix == ".npy":
            return StackData(_tilt_first(np.load(path, allow_pickle=False), tilt_index_axis, path, "the array"))
        if suffix == ".npz":
            with np.load(path, allow_pickle=False) as z:
                name = _pick(list(z.files), dataset, path, "array")
                return StackData(_tilt_first(z[name], tilt_index_axis, path, name))
        if suffix in (".tif", ".tiff"):
            import tifffile

            return StackData(_tilt_first(tifffile.imread(path), tilt_index_axis, path, "the TIFF stack"))
        if suffix in (".mrc", ".st", ".ali"):
            return _read_mrc(path, tilt_index_axis)
        if suffix in (".emd", ".h5", ".hdf5"):
            return _read_hdf5(path, dataset, tilt_index_axis)
        if suffix == ".mat":
            return _read_mat(path, dataset, tilt_index_axis)
    except TiltSeriesError:
        raise
    except Exception as exc:  # the libraries raise many types; name the file
        raise TiltSeriesError(f"{path}: could not read projections ({type(exc).__name__}: {exc})") from exc
    raise TiltSeriesError(f"{path}: unsupported projections file type {suffix!r}; expected one of {STACK_SUFFIXES}")


def _read_mrc(path: Path, tilt_index_axis: int | None) -> StackData:
    import mrcfile

    with mrcfile.open(path, permissive=True) as mrc:
        data = np.array(mrc.data)
        size = float(mrc.voxel_size.x)
        labels = [bytes(label).decode("ascii", "replace") for label in mrc.header.label[: int(mrc.header.nlabl)]]
    return StackData(_tilt_first(data, tilt_index_axis, path, "the MRC stack"), size if size > 0 else None, None, imod_tilt_axis_angle(labels))


def imod_tilt_axis_angle(labels: list[str]) -> float | None:
    """The last "Tilt axis angle = A" IMOD wrote into MRC labels (newstack, alignment), or None."""
    found = None
    for label in labels:
        match = re.search(r"tilt axis angle\s*=\s*([-+]?\d+(?:\.\d*)?)", label, re.IGNORECASE)
        if match:
            found = float(match.group(1))
    return found


def _read_hdf5(path: Path, dataset: str | None, tilt_index_axis: int | None) -> StackData:
    import h5py

    with h5py.File(path, "r") as f:
        if "data" in f and isinstance(f["data"], h5py.Group) and any(isinstance(g, h5py.Group) and "data" in g for g in f["data"].values()):
            # EMD: /data/<name>/{data, dim1, dim2, dim3}; a dimension named like "angle" holds the tilts.
            groups = [k for k, g in f["data"].items() if isinstance(g, h5py.Group) and "data" in g]
            group = f["data"][_pick(groups, dataset, path, "EMD data group")]
            array = np.array(group["data"])
            angles, axis = None, tilt_index_axis
            for d in range(array.ndim):
                dim = group.get(f"dim{d + 1}")
                if dim is None:
                    continue
                label = str(dim.attrs.get("name", b"")).lower() + str(dim.attrs.get("units", b"")).lower()
                if "angle" in label or "deg" in label:
                    angles = np.array(dim).astype(np.float64).reshape(-1)
                    axis = d if tilt_index_axis is None else tilt_index_axis
            return StackData(_tilt_first(array, axis, path, "the EMD data"), None, angles)
        names: list[str] = []
        f.visititems(lambda n, obj: names.append(n) if isinstance(obj, h5py.Dataset) and obj.ndim == 3 else None)
        name = _pick(names, dataset, path, "3D dataset")
        return StackData(_tilt_first(np.array(f[name]), tilt_index_axis, path, name))


def _mat_variables(path: Path) -> dict:
    """Variables of a .mat file: v5 through scipy, v7.3 (HDF5) through h5py with axes reversed."""
    import scipy.io

    import h5py

    if not h5py.is_hdf5(path):
        return {k: v for k, v in scipy.io.loadmat(path).items() if not k.startswith("__")}
    else:  # MATLAB v7.3 is HDF5 (with a 512-byte MATLAB header as its user block)
        with h5py.File(path, "r") as f:
            return {k: np.array(v).transpose() for k, v in f.items() if isinstance(v, h5py.Dataset)}


def _read_mat(path: Path, dataset: str | None, tilt_index_axis: int | None) -> StackData:
    variables = {k: v for k, v in _mat_variables(path).items() if np.ndim(v) == 3}
    name = _pick(list(variables), dataset, path, "3D variable")
    # MATLAB tomography packages (GENFIRE, RESIRE) store stacks as (H, W, N).
    return StackData(_tilt_first(variables[name], 2 if tilt_index_axis is None else tilt_index_axis, path, name))


def read_angles(path: str | Path, variable: str | None = None) -> np.ndarray:
    """Read tilt angles in degrees: ``(N,)`` single-axis, or ``(N, 3)`` Euler angles."""
    path = Path(path)
    if not path.is_file():
        raise TiltSeriesError(f"{path}: tilt angles file not found")
    suffix = path.suffix.lower()
    try:
        if suffix == ".npy":
            angles = np.load(path, allow_pickle=False)
        elif suffix == ".mat":
            variables = {k: v for k, v in _mat_variables(path).items() if np.ndim(v) == 2 and np.issubdtype(np.asarray(v).dtype, np.number)}
            angles = np.asarray(variables[_pick(list(variables), variable, path, "angle variable")])
        elif suffix in (".txt", ".tlt", ".rawtlt", ".csv", ".dat"):
            with warnings.catch_warnings():  # an empty file: the count check below says so in one line
                warnings.simplefilter("ignore", UserWarning)
                angles = np.loadtxt(path, delimiter="," if suffix == ".csv" else None, ndmin=1)
        else:
            raise TiltSeriesError(f"{path}: unsupported tilt angles file type {suffix!r}; expected one of {ANGLE_SUFFIXES}")
    except TiltSeriesError:
        raise
    except Exception as exc:
        raise TiltSeriesError(f"{path}: could not read tilt angles ({type(exc).__name__}: {exc})") from exc
    angles = np.asarray(angles, dtype=np.float64)
    if angles.ndim == 2 and 1 in angles.shape:
        angles = angles.reshape(-1)
    if angles.ndim == 2 and angles.shape[1] != 3 and angles.shape[0] == 3:
        angles = angles.T
    if not (angles.ndim == 1 or (angles.ndim == 2 and angles.shape[1] == 3)):
        raise TiltSeriesError(f"{path}: expected N tilt angles or N x 3 Euler angles, got shape {angles.shape}")
    return angles


def single_axis_from_euler(euler_deg: np.ndarray, where: str | Path = "tilt angles") -> np.ndarray:
    """Tilt angles (degrees, about our ``y`` axis) from ``(N, 3)`` Euler angles ``(phi, theta, psi)``.

    In the ZYZ convention shared by GENFIRE and RESIRE a single-axis tilt series has
    ``phi = psi = 0`` and ``theta`` the tilt; with the array axes read as (rows, cols) = (x, y)
    the peer's projections follow our convention exactly at ``tilt_axis="y"`` and the rotation
    centre ``n // 2`` (tests/test_convention.py).  General three-angle orientations are not
    supported yet: they are refused with a clear message rather than silently misread.
    """
    euler = np.asarray(euler_deg, dtype=np.float64)
    if euler.ndim != 2 or euler.shape[1] != 3:
        raise TiltSeriesError(f"{where}: expected N x 3 Euler angles (phi, theta, psi) in degrees, got shape {euler.shape}")
    off_axis = np.abs(euler[:, [0, 2]]).max() if len(euler) else 0.0
    if off_axis > 1e-6:
        raise TiltSeriesError(
            f"{where}: Euler angles with phi or psi != 0 (up to {off_axis:g} deg) describe a multi-axis "
            "series; only single-axis tilts (phi = psi = 0) are supported"
        )
    return euler[:, 1].copy()
