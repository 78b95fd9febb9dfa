"""Readers for the file formats tilt series come in.

Projection stacks: what microscopes and HyperSpy write goes through rosettasciio
(:mod:`dataparsers.rosetta`: Gatan ``.dm3``/``.dm4``, Velox ``.emd``, ``.hspy``/``.zspy``,
``.mrc``/``.st``/``.ali``, TIFF), with the pixel size and, where the file holds them, the tilt
angles.  Read here, where rosettasciio has no reader or loses what a tilt series needs:
``.npy``/``.npz``; ``.mat`` MATLAB v5 (scipy) and v7.3 (h5py, axes reversed as MATLAB stores
them column-major); plain ``.h5``/``.hdf5`` with one 3D dataset; the tomviz/Berkeley EMD layout
``data/<name>/data`` whose ``dim1..3`` hold the tilt angles, uneven steps included (rosettasciio
keeps only a first angle and a step).
Angle files: text (``.txt``, IMOD ``.tlt``/``.rawtlt``, ``.csv``), ``.npy``, ``.mat``.

Each reader returns what it found as a :class:`StackData`; errors are :class:`TiltSeriesError`
with a one-line message naming the file, the variable or dataset, and what was expected.
No nerfstudio import.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from .errors import TiltSeriesError
from .rosetta import LENGTH_TO_A, read_with_rosettasciio
from .stack_data import StackData, imod_tilt_axis_angle  # noqa: F401 (imported from here by callers)

STACK_SUFFIXES = (
    ".npy",
    ".npz",
    ".mat",
    ".h5",
    ".hdf5",
    ".emd",
    ".tif",
    ".tiff",
    ".mrc",
    ".st",
    ".ali",
    ".mrcz",
    ".dm3",
    ".dm4",
    ".hspy",
    ".zspy",
)
ANGLE_SUFFIXES = (".txt", ".tlt", ".rawtlt", ".csv", ".dat", ".npy", ".mat")


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
        if suffix == ".mat":
            return _read_mat(path, dataset, tilt_index_axis)
        if suffix == ".h5" or (suffix in (".emd", ".hdf5") and _ours_hdf5(path)):
            return _read_hdf5(path, dataset, tilt_index_axis)
        if suffix in (".tif", ".tiff"):
            return _read_tiff(path, dataset, tilt_index_axis)
        if suffix in STACK_SUFFIXES:
            return read_with_rosettasciio(path, dataset, tilt_index_axis)
    except TiltSeriesError:
        raise
    except Exception as exc:  # the libraries raise many types; name the file
        raise TiltSeriesError(f"{path}: could not read projections ({type(exc).__name__}: {exc})") from exc
    raise TiltSeriesError(f"{path}: unsupported projections file type {suffix!r}; expected one of {STACK_SUFFIXES}")


def _read_tiff(path: Path, dataset: str | None, tilt_index_axis: int | None) -> StackData:
    """A TIFF stack through rosettasciio (pixel size from its tags); a stack it cannot take
    (tifffile's plain pages, with few columns, read as samples) as tifffile reads it."""
    try:
        return read_with_rosettasciio(path, dataset, tilt_index_axis)
    except TiltSeriesError:
        raise
    except Exception:
        import tifffile

        return StackData(_tilt_first(tifffile.imread(path), tilt_index_axis, path, "the TIFF stack"))


def _ours_hdf5(path: Path) -> bool:
    """An HDF5 file rosettasciio would misread: the Berkeley EMD layout (whose angle dimension it
    reduces to a first angle and a step), or a plain HDF5 file that is not HyperSpy's."""
    import h5py

    if not h5py.is_hdf5(path):
        return False
    with h5py.File(path, "r") as f:
        if (
            "data" in f
            and isinstance(f["data"], h5py.Group)
            and any(isinstance(g, h5py.Group) and "data" in g for g in f["data"].values())
        ):
            return True
        return path.suffix.lower() == ".hdf5" and "Experiments" not in f


def _read_hdf5(path: Path, dataset: str | None, tilt_index_axis: int | None) -> StackData:
    import h5py

    with h5py.File(path, "r") as f:
        if (
            "data" in f
            and isinstance(f["data"], h5py.Group)
            and any(isinstance(g, h5py.Group) and "data" in g for g in f["data"].values())
        ):
            # EMD: /data/<name>/{data, dim1, dim2, dim3}; a dimension named like "angle" holds the tilts.
            groups = [k for k, g in f["data"].items() if isinstance(g, h5py.Group) and "data" in g]
            group = f["data"][_pick(groups, dataset, path, "EMD data group")]
            array = np.array(group["data"])
            angles, axis, lengths = None, tilt_index_axis, {}
            for d in range(array.ndim):
                dim = group.get(f"dim{d + 1}")
                if dim is None:
                    continue
                label = str(dim.attrs.get("name", b"")).lower() + str(dim.attrs.get("units", b"")).lower()
                if "angle" in label or "deg" in label:
                    angles = np.array(dim).astype(np.float64).reshape(-1)
                    axis = d if tilt_index_axis is None else tilt_index_axis
                else:
                    lengths[d] = _emd_step_A(dim)
            pixel = [v for d, v in lengths.items() if d != axis]
            size = (
                pixel[0]
                if len(pixel) == 2 and None not in pixel and abs(pixel[0] - pixel[1]) <= 1e-3 * pixel[0]
                else None
            )
            return StackData(_tilt_first(array, axis, path, "the EMD data"), size, angles)
        names: list[str] = []
        f.visititems(lambda n, obj: names.append(n) if isinstance(obj, h5py.Dataset) and obj.ndim == 3 else None)
        name = _pick(names, dataset, path, "3D dataset")
        return StackData(_tilt_first(np.array(f[name]), tilt_index_axis, path, name))


def _emd_step_A(dim) -> float | None:
    """The step in Å of a Berkeley EMD dimension whose units are a length, else None."""
    units = dim.attrs.get("units", b"")
    units = (units.decode() if isinstance(units, bytes) else str(units)).strip()
    factor = LENGTH_TO_A.get(units) or LENGTH_TO_A.get(units.lower())
    values = np.asarray(dim, dtype=np.float64).reshape(-1)
    if factor is None or len(values) < 2 or values[1] == values[0]:
        return None
    return float(abs(values[1] - values[0]) * factor)


def _mat_variables(path: Path) -> dict:
    """Variables of a .mat file: v5 through scipy, v7.3 (HDF5) through h5py with axes reversed."""
    import h5py
    import scipy.io

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
            variables = {
                k: v
                for k, v in _mat_variables(path).items()
                if np.ndim(v) == 2 and np.issubdtype(np.asarray(v).dtype, np.number)
            }
            angles = np.asarray(variables[_pick(list(variables), variable, path, "angle variable")])
        elif suffix in (".txt", ".tlt", ".rawtlt", ".csv", ".dat"):
            with warnings.catch_warnings():  # an empty file: the count check below says so in one line
                warnings.simplefilter("ignore", UserWarning)
                angles = np.loadtxt(path, delimiter="," if suffix == ".csv" else None, ndmin=1)
        else:
            raise TiltSeriesError(
                f"{path}: unsupported tilt angles file type {suffix!r}; expected one of {ANGLE_SUFFIXES}"
            )
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
        raise TiltSeriesError(
            f"{where}: expected N x 3 Euler angles (phi, theta, psi) in degrees, got shape {euler.shape}"
        )
    off_axis = np.abs(euler[:, [0, 2]]).max() if len(euler) else 0.0
    if off_axis > 1e-6:
        raise TiltSeriesError(
            f"{where}: Euler angles with phi or psi != 0 (up to {off_axis:g} deg) describe a multi-axis "
            "series; only single-axis tilts (phi = psi = 0) are supported"
        )
    return euler[:, 1].copy()
