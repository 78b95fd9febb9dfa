"""A film's sub-areas: tilt series cut from one field, each with its place in the film.

A sub-area is a tilt-series directory whose atoms come out in its own frame (Å about its tilt
centre), its ``offset_A`` (where that frame's origin lies in the film's frame) and its
interior (the detector less ``edge_px`` on each side: atoms near a sub-area's edge leave the
field at some tilts, and differ between neighbouring fits).

Two sources:

* :func:`published_subareas`: sub-area stacks as sub-area AET publishes them
  (``Projections_area<N>.mat`` with ``Proj_sub`` (x, y, tilt), ``angles.mat`` and
  ``alignPara.mat``'s ``CropCen`` and ``CropHalf``, voxels of the full volume);
* :func:`tile_series`: one large aligned series cut into overlapping sub-areas along the axis
  across the tilt axis and along it.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from dataparsers.errors import TiltSeriesError
from dataparsers.tilt_series_format import TiltSeries, load_tilt_series, write_tilt_series

EDGE_PX = (10, 4)
"""Pixels left out of a sub-area's interior at each edge, (across, along the tilt axis): the
sub-area AET data's own scoring interior (``../shared/data/ta_film/README.md``: 10 px in x, 4 in
y for sub-areas 131-151 x 61-77 px)."""


@dataclass
class SubArea:
    """One sub-area: ``name``, its tilt-series directory ``data``, ``offset_A`` (3,) of its
    frame in the film's, its detector ``shape_px`` and tilt centre ``centre_px`` (row, col), the
    pixel size, and ``edge_px`` (rows, cols) left out of its interior."""

    name: str
    data: Path
    offset_A: tuple[float, float, float]
    shape_px: tuple[int, int]
    centre_px: tuple[float, float]
    pixel_size_A: float
    edge_px: tuple[int, int] = EDGE_PX

    @property
    def interior_A(self) -> np.ndarray:
        """(2, 2) lower and upper (x, y) corners of the interior in the film's frame, Å."""
        lo = (np.array(self.edge_px, float) - np.array(self.centre_px)) * self.pixel_size_A
        hi = (
            np.array(self.shape_px, float) - 1 - np.array(self.edge_px) - np.array(self.centre_px)
        ) * self.pixel_size_A
        offset = np.asarray(self.offset_A[:2], dtype=np.float64)
        return np.stack([lo + offset, hi + offset])

    def to_json(self) -> dict:
        return {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(self).items()}

    @classmethod
    def from_json(cls, d: dict) -> SubArea:
        return cls(
            d["name"],
            Path(d["data"]),
            tuple(d["offset_A"]),
            tuple(d["shape_px"]),
            tuple(d["centre_px"]),
            float(d["pixel_size_A"]),
            tuple(d["edge_px"]),
        )


def write_plan(subareas: list[SubArea], path: Path) -> Path:
    """The sub-areas as ``film.json`` (what a resumed run reads back)."""
    Path(path).write_text(json.dumps([s.to_json() for s in subareas], indent=1) + "\n")
    return Path(path)


def read_plan(path: Path) -> list[SubArea]:
    return [SubArea.from_json(d) for d in json.loads(Path(path).read_text())]


def mat_variable(path: Path, name: str) -> np.ndarray:
    """Variable ``name`` of a MATLAB file as float64; ``TiltSeriesError`` naming the file where it
    is missing or lacks the variable."""
    from dataparsers.readers import _mat_variables

    if not path.is_file():
        raise TiltSeriesError(f"{path}: not found")
    variables = _mat_variables(path)
    if name not in variables:
        raise TiltSeriesError(f"{path}: no variable {name!r}; it holds {sorted(variables)}")
    return np.asarray(variables[name], dtype=np.float64)


def published_subareas(
    data_dir: Path,
    areas: list[int],
    out_dir: Path,
    pixel_size_A: float,
    full_centre_vox: tuple[float, float, float],
    euler_convention: str = "zyx",
) -> list[SubArea]:
    """The sub-areas ``areas`` (1-based rows of ``alignPara.mat``) of a sub-area AET data set
    written as tilt-series directories under ``out_dir``.  A sub-area's frame is centred on
    ``CropHalf`` of its crop, so its origin lies at ``(CropCen - full_centre_vox) *
    pixel_size_A`` in the film's frame (a sub-volume's 0-based index ``i`` is the full volume's
    1-based ``CropCen - CropHalf + i``) (``full_centre_vox``: the film frame's origin, 1-based
    voxels of the full volume).  ``euler_convention`` names the axes of N x 3 Euler angles
    (sub-area AET is RESIRE's, whose angles are Z-Y-X).  A file that cannot be read raises
    ``TiltSeriesError`` naming it."""
    data_dir, out_dir = Path(data_dir), Path(out_dir)
    align = data_dir / "alignPara.mat"
    cen_all, half_all = mat_variable(align, "CropCen"), mat_variable(align, "CropHalf")
    angles = mat_variable(data_dir / "angles.mat", "angle")  # N x 3 Euler angles are kept (TiltSeries.euler_deg)
    angles = angles if angles.ndim == 2 and angles.shape[1] == 3 else angles.reshape(-1)
    missing = [a for a in areas if not 1 <= a <= len(cen_all)]
    if missing:  # before anything is written
        raise TiltSeriesError(f"{align}: no sub-area {missing[0]}; it holds 1-{len(cen_all)}")
    out = []
    for area in areas:
        cen, half = cen_all[area - 1], half_all[area - 1]
        name = f"area{area}"
        target = out_dir / name
        if not (target / "tilt_series.json").is_file():
            stack = mat_variable(data_dir / f"Projections_area{area}.mat", "Proj_sub")  # (x, y, tilt)
            write_tilt_series(
                target,
                np.moveaxis(stack, 2, 0).astype(np.float32),
                angles,
                pixel_size_A,
                centre_px=(float(half[0]), float(half[1])),
                euler_convention=euler_convention,
            )
        out.append(subarea_at(name, target, (cen - np.asarray(full_centre_vox)) * pixel_size_A))
    return out


def subarea_at(name: str, data: Path, offset_A) -> SubArea:
    """The sub-area ``name`` whose tilt-series directory is ``data`` (its detector shape, tilt
    centre and pixel size read there), its frame at ``offset_A`` (3,) in the film's."""
    series = load_tilt_series(data)
    return SubArea(
        name,
        Path(data),
        tuple(float(v) for v in offset_A),
        tuple(int(v) for v in series.projections.shape[1:]),
        tuple(float(v) for v in series.centre_px),
        float(series.pixel_size_A),
    )


OVERLAP = 7
"""Sub-areas that cover each point of a film: sub-area AET's own (the Ta film's strips put each
point inside about 7 sub-areas, ``../shared/data/ta_film/README.md``)."""
WIDTH_PER_THICKNESS = 2.0
"""A tile's width across the tilt axis per thickness of film: the Ta film's sub-areas are 42-49
Å across for a film whose atoms spread over 20-35 Å in depth (the data's README)."""


def film_thickness_A(series: TiltSeries) -> float:
    """The film's thickness, Å, read from the series: the views averaged along the tilt axis are
    one sinogram of the film's mean cross-section, filtered back-projected (Hann); the
    thickness is the full width at half maximum of its profile across the slab above the
    profile's median (the narrower of the two axes of a film wider than it is thick).  On Pd
    slabs 8-20 Å thick (tilts -60..60) it read 9.0, 13.5, 16.5 and 19.5 Å for 8, 12, 16 and 20."""
    from gaussian_atoms_method.physics.reconstruction import filtered_backprojection

    h = series.projections.shape[1]
    mean = series.projections.mean(axis=2)  # (V, H): the film's mean section
    shift = int(round(h // 2 - float(series.centre_px[0])))
    sinogram = np.roll(mean, shift, axis=1).T[None]  # (1, H, V), the tilt centre at H // 2
    section = np.clip(np.asarray(filtered_backprojection(sinogram, series.angles_deg, "hann"))[0], 0, None)

    def fwhm(profile: np.ndarray) -> float:
        profile = profile - np.median(profile)  # the noise's floor: most depths of the square section are empty
        above = np.flatnonzero(profile >= profile.max() / 2)
        return float(above[-1] - above[0] + 1) if len(above) else float(len(profile))

    return min(fwhm(section.mean(axis=0)), fwhm(section.mean(axis=1))) * series.pixel_size_A


def default_tiling(series: TiltSeries) -> tuple[tuple[int, int], tuple[int, int]]:
    """Tile size and step (pixels) for ``series``: :data:`WIDTH_PER_THICKNESS` times the film's
    thickness across the tilt axis (at most the field), the whole field along it, and
    :data:`OVERLAP` tiles over each point."""
    h, w = series.projections.shape[1:]
    across = min(
        h, max(2 * EDGE_PX[0] + 8, round(WIDTH_PER_THICKNESS * film_thickness_A(series) / series.pixel_size_A))
    )
    return (across, w), (max(1, round(across / OVERLAP)), w)


def tile_series(series: TiltSeries, size_px: tuple[int, int], step_px: tuple[int, int], out_dir: Path) -> list[SubArea]:
    """Cut ``series`` into sub-areas of ``size_px`` (rows across the tilt axis, cols along it)
    every ``step_px``, each written as a tilt-series directory under ``out_dir``, as sub-area AET
    cuts them: each view's crop follows the sub-area's centre on the film's mid-plane (a point
    ``d`` across the axis projects to ``d cos(tilt)``; sampled linearly between pixels), so each
    sub-area turns about its own centre.  The film's frame is the series' own (Å about its tilt
    centre).  The last tiles end at the field's edge.  Series about ``y`` with the axis along the
    columns only (a ``ValueError`` otherwise); with Euler angles each crop follows the tile's
    centre as each view's full orientation projects it."""
    from scipy.ndimage import map_coordinates

    if series.tilt_axis != "y" or series.tilt_axis_angle_deg != 0.0:
        raise ValueError("tiling needs the tilt axis along the detector's columns (tilt_axis y, tilt_axis_angle_deg 0)")
    h, w = series.projections.shape[1:]
    size = (min(int(size_px[0]), h), min(int(size_px[1]), w))
    if min(step_px) < 1 or min(size) < 1:
        raise ValueError(f"tile size {size_px} and step {step_px} must be positive")
    smallest = tuple(2 * e + 1 for e in EDGE_PX)
    if size[0] < smallest[0] or size[1] < smallest[1]:
        raise ValueError(
            f"tile size {size[0]} x {size[1]} px leaves no interior (its edges take {EDGE_PX[0]} px across the axis "
            f"and {EDGE_PX[1]} along it on each side); use at least {smallest[0]} x {smallest[1]}"
        )

    def starts(extent: int, length: int, step: int) -> list[int]:
        out = list(range(0, max(extent - length, 0) + 1, step))
        return out if out[-1] == extent - length else out + [extent - length]

    cr, cc = (float(v) for v in series.centre_px)
    cos = np.cos(np.deg2rad(series.angles_deg))
    # With Euler angles a view turns in its plane too: the crop follows the detector position
    # D (across, along, 0) of the tile's centre, so each tile keeps the series' orientations.
    in_plane = series.detector_axes()[:, :2, :2] if series.euler_deg is not None else None
    middle = ((size[0] - 1) / 2.0, (size[1] - 1) / 2.0)
    out = []
    for r in starts(h, size[0], step_px[0]):
        for c in starts(w, size[1], step_px[1]):
            across_px = r + middle[0] - cr  # the tile's centre across the axis, from the tilt centre
            along_px = c + middle[1] - cc
            # (V, 2) the tile centre's detector position in each view, from the tilt centre
            shifts = (
                np.c_[across_px * cos, np.full(len(cos), along_px)]
                if in_plane is None
                else in_plane @ np.array([across_px, along_px])
            )
            views = np.empty((len(cos), *size), dtype=np.float32)
            for v, (shift_row, shift_col) in enumerate(shifts):
                rows = cr + shift_row - middle[0] + np.arange(size[0], dtype=np.float64)
                cols = c + (shift_col - along_px) + np.arange(size[1], dtype=np.float64)
                grid = np.meshgrid(rows, cols, indexing="ij")
                views[v] = map_coordinates(series.projections[v], grid, order=1, mode="nearest")
            name = f"tile_r{r}_c{c}"
            target = write_tilt_series(
                Path(out_dir) / name,
                views,
                series.orientations_deg,
                series.pixel_size_A,
                centre_px=middle,
                species=series.species,
                euler_convention=series.euler_convention,
            )
            offset = (across_px * series.pixel_size_A, along_px * series.pixel_size_A, 0.0)
            out.append(SubArea(name, target, offset, size, middle, series.pixel_size_A))
    return out
