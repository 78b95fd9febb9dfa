"""Projection stacks through rosettasciio, HyperSpy's I/O library: the formats microscopes write.

Gatan ``.dm3``/``.dm4``, Velox and Berkeley ``.emd``, HyperSpy ``.hspy``/``.zspy``, ``.mrc``
(and IMOD's ``.st``/``.ali``, FEI extended headers with their tilts), TIFF with its pixel-size
tags.  A signal dictionary (``data``, ``axes``, ``metadata``, ``original_metadata``) becomes a
:class:`~dataparsers.stack_data.StackData`:

* the tilt index is the axis whose units are an angle, else the navigation axis;
* the tilt angles are that axis's values when its units are an angle, else
  ``metadata.Tomography.tilts`` (etspy's place for them), else an FEI header's per-frame
  ``a_tilt``;
* the pixel size is the image axes' scale in Å, when their units are a length (nm, Å, pm, µm)
  and the two axes agree.

No nerfstudio import; rosettasciio is imported when a file needs it.
"""

from __future__ import annotations

import importlib
from pathlib import Path

import numpy as np

from .errors import TiltSeriesError
from .stack_data import StackData, imod_tilt_axis_angle

PLUGINS = {
    ".dm3": "digitalmicrograph",
    ".dm4": "digitalmicrograph",
    ".emd": "emd",
    ".hspy": "hspy",
    ".hdf5": "hspy",
    ".zspy": "zspy",
    ".mrc": "mrc",
    ".st": "mrc",
    ".ali": "mrc",
    ".mrcz": "mrcz",
    ".tif": "tiff",
    ".tiff": "tiff",
}
"""The rosettasciio plugin that reads each suffix."""

LENGTH_TO_A = {
    "a": 1.0,
    "å": 1.0,
    "Å": 1.0,
    "angstrom": 1.0,
    "angstroms": 1.0,
    "ang": 1.0,
    "\\aa": 1.0,
    "nm": 10.0,
    "pm": 0.01,
    "um": 1e4,
    "µm": 1e4,
    "μm": 1e4,
}
ANGLE_TO_DEG = {
    "deg": 1.0,
    "degree": 1.0,
    "degrees": 1.0,
    "°": 1.0,
    "rad": 180.0 / np.pi,
    "radian": 180.0 / np.pi,
    "radians": 180.0 / np.pi,
    "mrad": 0.18 / np.pi,
}
RELATIVE_PIXEL_MISMATCH = 1e-3
"""Rows and columns whose pixel sizes differ by more than this are not square pixels (files
written in float32 differ by 1e-7 between the two; a real anisotropy is a percent or more)."""


def _units(axis: dict) -> str:
    units = axis.get("units")
    return "" if units is None or str(units) == "<undefined>" else str(units).strip()


def axis_values(axis: dict) -> np.ndarray:
    """The coordinates of one rosettasciio axis: its ``axis`` array, or ``offset + scale * i``."""
    if axis.get("axis") is not None:
        return np.asarray(axis["axis"], dtype=np.float64).reshape(-1)
    return float(axis.get("offset", 0.0) or 0.0) + float(axis.get("scale", 1.0) or 1.0) * np.arange(int(axis["size"]))


def _angle_factor(axis: dict) -> float | None:
    return ANGLE_TO_DEG.get(_units(axis).lower())


def pixel_size_A(axes: list[dict], path: Path) -> float | None:
    """The image axes' common scale in Å, or None when their units are not a length."""
    sizes = []
    for axis in axes:
        factor = LENGTH_TO_A.get(_units(axis)) or LENGTH_TO_A.get(_units(axis).lower())
        if factor is None or axis.get("axis") is not None:
            return None
        sizes.append(float(axis.get("scale", 1.0)) * factor)
    if not sizes or min(sizes) <= 0:
        return None
    if max(sizes) > min(sizes) * (1 + RELATIVE_PIXEL_MISMATCH):
        raise TiltSeriesError(
            f"{path}: pixels of {' x '.join(f'{s:.4g}' for s in sizes)} Å; square pixels expected (resample the stack)"
        )
    return float(np.mean(sizes))


def _metadata_tilts(signal: dict) -> np.ndarray | None:
    tomography = (signal.get("metadata") or {}).get("Tomography") or {}
    tilts = tomography.get("tilts")
    if tilts is not None and np.size(tilts) > 0:
        return np.asarray(tilts, dtype=np.float64).reshape(-1)
    fei = (signal.get("original_metadata") or {}).get("fei_header")
    if fei is not None:
        try:
            return np.asarray(fei["a_tilt"], dtype=np.float64).reshape(-1)
        except (KeyError, ValueError, TypeError, IndexError):
            return None
    return None


def _mrc_labels(signal: dict) -> list[str]:
    """The text labels of an MRC header (rosettasciio stores them as one hex string)."""
    labels = ((signal.get("original_metadata") or {}).get("std_header") or {}).get("LABELS")
    if labels is None:
        return []
    try:
        raw = bytes.fromhex(labels) if isinstance(labels, str) else bytes(np.asarray(labels, dtype=np.uint8))
    except (ValueError, TypeError):
        return []
    text = raw.decode("ascii", "replace")
    return [text[i : i + 80] for i in range(0, len(text), 80)]


def _pick_signal(signals: list[dict], dataset: str | None, path: Path) -> dict:
    stacks = [s for s in signals if np.ndim(s["data"]) == 3]
    if not stacks:
        shapes = [tuple(np.shape(s["data"])) for s in signals]
        raise TiltSeriesError(f"{path}: holds no 3D stack (signals of shape {shapes}); a tilt series is (N, H, W)")
    titles = [str(((s.get("metadata") or {}).get("General") or {}).get("title", "")) for s in stacks]
    if dataset is not None:
        if dataset not in titles:
            raise TiltSeriesError(f"{path}: no signal titled {dataset!r}; it holds {titles}")
        return stacks[titles.index(dataset)]
    if len(stacks) > 1:
        raise TiltSeriesError(f"{path}: holds {len(stacks)} 3D signals {titles}; name the one to use (dataset)")
    return stacks[0]


def stack_from_signal(signal: dict, path: Path, tilt_index_axis: int | None = None) -> StackData:
    """A :class:`~dataparsers.stack_data.StackData` from one rosettasciio signal dictionary
    (also what a HyperSpy signal's ``as_dictionary()`` gives)."""
    data = np.asarray(signal["data"])
    axes = [dict(a) for a in signal["axes"]]
    if data.ndim != 3 or len(axes) != 3:
        raise TiltSeriesError(f"{path}: expected a 3D stack (N, H, W), got shape {data.shape}")
    for k, axis in enumerate(axes):
        axis.setdefault("size", data.shape[k])
    if tilt_index_axis is None:
        angular = [k for k, a in enumerate(axes) if _angle_factor(a) is not None]
        navigation = [k for k, a in enumerate(axes) if a.get("navigate")]
        tilt_index_axis = angular[0] if angular else (navigation[0] if len(navigation) == 1 else 0)
    if not -3 <= tilt_index_axis < 3:
        raise TiltSeriesError(f"{path}: tilt_index_axis must be 0, 1 or 2, got {tilt_index_axis}")
    tilt_index_axis %= 3
    tilt = axes[tilt_index_axis]
    factor = _angle_factor(tilt)
    angles = axis_values(tilt) * factor if factor is not None else _metadata_tilts(signal)
    if angles is not None and len(angles) != data.shape[tilt_index_axis]:
        angles = None  # metadata for another shape (a cropped stack): the user gives the angles
    image_axes = [a for k, a in enumerate(axes) if k != tilt_index_axis]
    return StackData(
        np.moveaxis(data, tilt_index_axis, 0),
        pixel_size_A(image_axes, path),
        angles,
        imod_tilt_axis_angle(_mrc_labels(signal)),
    )


def read_with_rosettasciio(path: Path, dataset: str | None, tilt_index_axis: int | None) -> StackData:
    """Read ``path`` with the rosettasciio plugin of its suffix (:data:`PLUGINS`)."""
    suffix = path.suffix.lower()
    try:
        plugin = importlib.import_module(f"rsciio.{PLUGINS[suffix]}")
    except ImportError as exc:
        raise TiltSeriesError(
            f"{path}: reading {suffix} needs rosettasciio (pip install rosettasciio): {exc}"
        ) from None
    signal = _pick_signal(plugin.file_reader(str(path)), dataset, path)
    stack = stack_from_signal(signal, path, tilt_index_axis)
    if suffix in (".mrc", ".st", ".ali") and not _mrc_header_has_size(signal):
        stack.pixel_size_A = None  # rosettasciio then reports a scale of 1 nm
        # rosettasciio writes MRC through mrcz, whose header keeps the pixel size where only mrcz reads it.
        try:
            stack.pixel_size_A = _mrcz_pixel_size(path, dataset, tilt_index_axis)
        except Exception:  # not an mrcz file: the size stays unknown and the user gives it
            pass
    return stack


def _mrc_header_has_size(signal: dict) -> bool:
    """Whether an MRC header states a pixel size (cell length and sampling both set)."""
    header = (signal.get("original_metadata") or {}).get("std_header") or {}
    try:
        return all(float(header[k]) > 0 for k in ("MX", "MY", "Xlen", "Ylen"))
    except (KeyError, TypeError, ValueError):
        return False


def _mrcz_pixel_size(path: Path, dataset: str | None, tilt_index_axis: int | None) -> float | None:
    plugin = importlib.import_module("rsciio.mrcz")
    return stack_from_signal(
        _pick_signal(plugin.file_reader(str(path)), dataset, path), path, tilt_index_axis
    ).pixel_size_A
