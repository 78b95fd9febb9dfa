"""The ``tilt_series.json`` directory: what a tilt series is on disk, read and written.

A directory holds ``tilt_series.json``::

    {"projections": "projections.npy",   # (N, H, W) float array
     "angles_deg": "angles.txt",         # N tilt angles in degrees, one per line (or N rows of
                                         # Euler angles phi theta psi)
     "euler_convention": "zyz",          # optional, the Euler angles' axes: "zyz" (default, as
                                         # GENFIRE writes them) or "zyx" (as RESIRE does)
     "pixel_size_A": 0.25,
     "tilt_axis": "y",                   # optional, "y" (default) or "x"
     "contrast": "adf",                  # optional, what the views show: "adf" (default) or
                                         # "phase" (ptychographic phase images)
     "truth": "atoms_true.xyz",          # optional, the true atoms
     "origin_A": [35.0, 35.0, 35.0],     # optional, the tilt centre in the truth file's frame
     "centre_px": [63.5, 63.5],          # optional, detector pixel (row, col) of the tilt
                                         # centre; default the middle, (H-1)/2, (W-1)/2
     "volume": "potential_volume.npy"}   # optional, the true potential (n, n, n) blurred like
                                         # the data, voxel i at (i - (n-1)/2) * volume_voxel_size_A

Paths are relative to the directory.  Reading validates everything and raises
:class:`TiltSeriesError` with a one-line message naming the file and the problem.  This module
does not import nerfstudio.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gaussian_atoms_method.physics.geometry import (
    EULER_CONVENTIONS,
    TILT_AXES,
    detector_axes_of,
    imod_axis_angle,
)
from gaussian_atoms_method.physics.noise import MIN_SIDE_PX

from . import views
from .errors import TiltSeriesError
from .manifest import MANIFEST, read_manifest, update_manifest, write_manifest
from .readers import read_angles, read_stack

__all__ = ["MANIFEST", "TiltSeries", "TiltSeriesError", "load_tilt_series", "write_tilt_series", "update_manifest"]


CONTRASTS = ("adf", "phase")
"""What a series' views show (:attr:`TiltSeries.contrast`)."""


MANIFEST_WORDS = ("pixel", "axis", "origin", "centre", "species", "convention", "contrast")
"""Words of a refusal that names the manifest (or its option), not the projections' file."""


@dataclass
class TiltSeries:
    """A validated tilt series.

    Attributes
    ----------
    projections : (N, H, W) float32 array
        Line integrals of the potential (any units; negative values allowed).
    angles_deg : (N,) float64 array
    pixel_size_A : float
    tilt_axis : {"y", "x"}
    origin_A : (3,) float64 array
        Position of the tilt centre in the output (truth) frame, Å.
    truth_path : Path or None
    source : Path or None
        Where it was read from.
    centre_px : (2,) float64 array or None
        Detector (row, column) pixel index onto which the tilt centre projects; None means the
        middle of the detector.
    tilt_axis_angle_deg : float
        Angle of the tilt axis in the recorded images, from the detector direction ``tilt_axis``
        names (:mod:`gaussian_atoms_method.physics.geometry`: counterclockwise with the rows
        pointing up, as IMOD shows a stack).
    species : tuple of str
        The elements the specimen holds (``("Ta",)``, ``("Fe", "Pt")``); () when not given.  They
        set the material's hard core (:mod:`gaussian_atoms_method.atoms.hard_core`).
    euler_deg : (N, 3) float64 array or None
        Euler angles ``(phi, theta, psi)`` per view, as GENFIRE and RESIRE refine them (given
        as ``angles_deg`` of shape (N, 3)); ``angles_deg`` then holds ``theta``.  None when every
        ``phi`` and ``psi`` is zero: a single-axis series.  The fit projects with the full
        orientation (:meth:`detector_axes`); the start back-projects about ``theta`` alone, so
        the views may leave the single axis by no more than :data:`dataparsers.views.MAX_START_OFFSET_A`.
    euler_convention : {"zyz", "zyx"}
        The axes of ``euler_deg``: Z-Y-Z as GENFIRE writes them (the default), Z-Y-X as RESIRE.
    pixel_size_source : str
        Where ``pixel_size_A`` came from (an option, a manifest, a file's header), as a run says it.
    view_indices : (N,) int array
        Each view's index in the file it was read from (``drop_views`` leaves some out), of
        ``views_given`` (default N).
    noise_path : Path or None
        A replica's own noise: the (``views_given``, H, W) field its views were drawn with, in
        the projections' units (manifest key ``noise``; :func:`~gaussian_atoms_method.harness.replica.write_replica`
        writes it), against which a run checks the noise it reads; None for measured views.
    contrast : {"adf", "phase"}
        What the views show: incoherent ADF-STEM images, a power of the projected potential
        through a probe (the default), or ptychographic phase images, the projected potential
        through the aperture's transfer (:mod:`gaussian_atoms_method.physics.phase`).  The run's own
        replica draws its atoms so (:mod:`gaussian_atoms_method.engine.own_floor`).
    """

    projections: np.ndarray
    angles_deg: np.ndarray
    pixel_size_A: float
    tilt_axis: str = "y"
    origin_A: np.ndarray = field(default_factory=lambda: np.zeros(3))
    truth_path: Path | None = None
    source: Path | None = None
    centre_px: np.ndarray | None = None
    tilt_axis_angle_deg: float = 0.0
    species: tuple = ()
    euler_deg: np.ndarray | None = None
    euler_convention: str = "zyz"
    pixel_size_source: str = ""
    view_indices: np.ndarray | None = None
    views_given: int | None = None
    noise_path: Path | None = None
    contrast: str = "adf"

    def __post_init__(self) -> None:
        where = str(self.source) if self.source is not None else "tilt series"
        proj = np.asarray(self.projections)
        if proj.ndim != 3:
            raise TiltSeriesError(f"{where}: projections must be a 3D array (N, H, W), got shape {proj.shape}")
        if not np.issubdtype(proj.dtype, np.number) or np.iscomplexobj(proj):
            raise TiltSeriesError(f"{where}: projections must be real numbers, got dtype {proj.dtype}")
        if min(proj.shape) == 0:
            raise TiltSeriesError(f"{where}: projections are empty, shape {proj.shape}")
        if min(proj.shape[1:]) < MIN_SIDE_PX:
            raise TiltSeriesError(
                f"{where}: projections of {proj.shape[1]} x {proj.shape[2]} pixels; at least {MIN_SIDE_PX} x "
                f"{MIN_SIDE_PX} are needed (is the stack's axis order right? see tilt_index_axis)"
            )
        angles = np.asarray(self.angles_deg, dtype=np.float64)
        if angles.ndim == 2 and angles.shape[1] == 3:  # Euler angles (phi, theta, psi)
            self.euler_deg, angles = angles, angles[:, 1]
        angles = angles.reshape(-1)
        if len(angles) != proj.shape[0]:
            raise TiltSeriesError(f"{where}: {len(angles)} tilt angles for {proj.shape[0]} projections")
        if not np.all(np.isfinite(angles)):
            raise TiltSeriesError(f"{where}: tilt angles hold NaN/Inf")
        indices = np.arange(len(angles)) if self.view_indices is None else np.asarray(self.view_indices, np.int64)
        views.unusable_views(proj, angles, indices, where)
        views.dark_atoms(proj, where)
        self.projections, self.view_indices = proj.astype(np.float32, copy=False), indices
        self.views_given = int(self.views_given if self.views_given is not None else len(angles))
        views.undecidable_depth(angles, where)
        uniq, counts = np.unique(angles, return_counts=True)
        if np.any(counts > 1):
            raise TiltSeriesError(f"{where}: duplicate tilt angle(s) {uniq[counts > 1].tolist()} deg")
        self.angles_deg = angles
        if not (np.isfinite(self.pixel_size_A) and self.pixel_size_A > 0):
            raise TiltSeriesError(f"{where}: pixel_size_A must be a positive number of Å, got {self.pixel_size_A}")
        self.pixel_size_A = float(self.pixel_size_A)
        views.implausible_pixel_size(proj, self.pixel_size_A, where, self.pixel_size_source)
        if self.tilt_axis not in TILT_AXES:
            raise TiltSeriesError(f"{where}: tilt_axis must be one of {list(TILT_AXES)}, got {self.tilt_axis!r}")
        origin = np.asarray(self.origin_A, dtype=np.float64).reshape(-1)
        if origin.shape != (3,) or not np.all(np.isfinite(origin)):
            raise TiltSeriesError(f"{where}: origin_A must be three finite numbers (Å), got {self.origin_A!r}")
        self.origin_A = origin
        if self.centre_px is None:
            self.centre_px = (np.array(proj.shape[1:], dtype=np.float64) - 1) / 2.0
        centre = np.asarray(self.centre_px, dtype=np.float64).reshape(-1)
        if centre.shape != (2,) or not np.all(np.isfinite(centre)):
            raise TiltSeriesError(
                f"{where}: centre_px must be two finite pixel indices (row, col), got {self.centre_px!r}"
            )
        self.centre_px = centre
        try:
            self.tilt_axis_angle_deg = float(self.tilt_axis_angle_deg)
        except (TypeError, ValueError):
            raise TiltSeriesError(
                f"{where}: tilt_axis_angle_deg must be a number of degrees, got {self.tilt_axis_angle_deg!r}"
            ) from None
        if not np.isfinite(self.tilt_axis_angle_deg):
            raise TiltSeriesError(f"{where}: tilt_axis_angle_deg must be finite, got {self.tilt_axis_angle_deg}")
        if self.contrast not in CONTRASTS:
            raise TiltSeriesError(f"{where}: contrast must be one of {list(CONTRASTS)}, got {self.contrast!r}")
        if self.euler_convention not in EULER_CONVENTIONS:
            raise TiltSeriesError(
                f"{where}: euler_convention must be one of {list(EULER_CONVENTIONS)}, got {self.euler_convention!r}"
            )
        if self.euler_deg is not None:
            self.euler_deg = self._checked_euler(where, angles)
        from gaussian_atoms_method.atoms.hard_core import SpeciesError, parse_species

        try:
            self.species = parse_species(self.species)
        except SpeciesError as exc:
            raise TiltSeriesError(f"{where}: {exc}") from None

    def _checked_euler(self, where: str, theta: np.ndarray) -> np.ndarray | None:
        """The Euler angles, validated; None where every phi and psi is zero."""
        euler = np.asarray(self.euler_deg, dtype=np.float64)
        if euler.shape != (len(theta), 3) or not np.all(np.isfinite(euler)):
            raise TiltSeriesError(
                f"{where}: Euler angles must be N x 3 finite numbers (phi, theta, psi) for {len(theta)} projections, "
                f"got shape {euler.shape}"
            )
        if not np.array_equal(euler[:, 1], theta):
            raise TiltSeriesError(f"{where}: the Euler angles' theta column differs from the tilt angles")
        if not np.any(euler[:, [0, 2]]):
            return None
        if self.tilt_axis != "y" or self.tilt_axis_angle_deg:
            raise TiltSeriesError(
                f"{where}: Euler angles give the whole orientation of each view (tilting about y, as GENFIRE and "
                f"RESIRE); tilt_axis must be 'y' and tilt_axis_angle_deg 0, got {self.tilt_axis!r} and "
                f"{self.tilt_axis_angle_deg:g}"
            )
        offset = views.start_offset_A(
            euler, self.projections.shape[1:], self.centre_px, self.pixel_size_A, self.euler_convention
        )
        if offset > views.MAX_START_OFFSET_A:
            off_axis = np.abs(euler[:, [0, 2]]).max()
            raise TiltSeriesError(
                f"{where}: Euler angles with phi or psi up to {off_axis:g} deg move the field's corners {offset:.2f} Å "
                f"from where theta alone puts them (the start back-projects about theta; at most "
                f"{views.MAX_START_OFFSET_A:g} Å): series tilted in more than one direction are not supported"
            )
        return euler

    @property
    def orientations_deg(self) -> np.ndarray:
        """The views' angles as given: the (N, 3) Euler angles where there are any, else the
        (N,) tilts."""
        return self.angles_deg if self.euler_deg is None else self.euler_deg

    def detector_axes(self) -> np.ndarray:
        """(N, 3, 3) float64: each view's detector rows, columns and beam in the world
        (:func:`~gaussian_atoms_method.physics.geometry.detector_axes_of`)."""
        return detector_axes_of(self.orientations_deg, self.tilt_axis, self.tilt_axis_angle_deg, self.euler_convention)

    @property
    def n_views(self) -> int:
        return self.projections.shape[0]

    @property
    def image_shape(self) -> tuple[int, int]:
        return self.projections.shape[1], self.projections.shape[2]


def load_tilt_series(
    data: str | Path,
    projections: str | Path | None = None,
    angles_deg: str | Path | None = None,
    pixel_size_A: float | None = None,
    tilt_axis: str | None = None,
    truth: str | Path | None = None,
    dataset: str | None = None,
    tilt_index_axis: int | None = None,
    angles_variable: str | None = None,
    centre_px=None,
    tilt_axis_angle_deg: float | None = None,
    species: str | None = None,
    euler_convention: str | None = None,
    drop_views=None,
    contrast: str | None = None,
) -> TiltSeries:
    """Read a tilt series from a directory with ``tilt_series.json`` and/or explicit options.

    Options given here override the manifest's entries; relative paths are taken relative to
    ``data`` (a directory, or the manifest file itself).  Projections and angles go through
    :mod:`dataparsers.readers` (numpy, TIFF, MRC, EMD/HDF5, MATLAB; text, IMOD .tlt, .mat
    angles).  ``dataset`` names the variable or dataset inside a file that holds several,
    ``tilt_index_axis`` the array axis of the tilt index, ``angles_variable`` the variable of
    a .mat angle file; N x 3 Euler angles are kept (:attr:`TiltSeries.euler_deg`), about the
    axes ``euler_convention`` names ("zyz" as GENFIRE, the default; "zyx" as RESIRE).  Without
    a pixel size, an MRC header's is used; without an angle file, an EMD file's angle dimension;
    without a tilt-axis angle, the one IMOD writes into an MRC header's labels (with
    ``tilt_axis`` "x", IMOD's reference direction, unless given).  ``species`` ("Ta", "Fe,Pt")
    names the specimen's elements (manifest key ``species``: a string or a list); ``drop_views``
    the views left out (:func:`dataparsers.views.views_to_drop`: "3,7", "-40deg"); ``contrast``
    what the views show (:attr:`TiltSeries.contrast`).
    """

    data = Path(data)
    if data.is_file() and data.suffix == ".json":
        manifest_path, root = data, data.parent
    elif data.is_file() and projections is None:  # a projection file: its folder holds no manifest to read
        manifest_path, root, projections = data.parent / (MANIFEST + ".absent"), data.parent, data.name
    else:
        manifest_path, root = data / MANIFEST, data
    if not root.exists():
        raise TiltSeriesError(f"{root}: data directory not found")
    manifest = read_manifest(manifest_path) if manifest_path.is_file() else {}
    if not manifest_path.is_file() and projections is None:
        raise TiltSeriesError(f"{manifest_path}: not found, and no projections option given")
    where = manifest_path if manifest_path.is_file() else root

    def pick(option, key):
        return option if option is not None else manifest.get(key)

    proj_name, angles_name, px = (
        pick(projections, "projections"),
        pick(angles_deg, "angles_deg"),
        pick(pixel_size_A, "pixel_size_A"),
    )
    if proj_name is None:
        raise TiltSeriesError(f"{where}: 'projections' is missing (give it in {MANIFEST} or as an option)")
    proj_path = root / proj_name
    stack = read_stack(proj_path, pick(dataset, "dataset"), pick(tilt_index_axis, "tilt_index_axis"))
    proj = stack.projections
    px_source = "the pixel_size_A option" if pixel_size_A is not None else str(manifest_path)
    if px is None:
        px, px_source = stack.pixel_size_A, f"{proj_path.name}'s header"
    if px is None:
        raise TiltSeriesError(
            f"{where}: 'pixel_size_A' is missing (give it in {MANIFEST} or as an option; {proj_path.name} has none in "
            f"its header)"
        )
    px_where = "--pixel-size-A" if pixel_size_A is not None else where
    try:
        px = float(px)
    except (TypeError, ValueError):
        raise TiltSeriesError(f"{px_where}: pixel_size_A must be a number of Å, got {px!r}") from None
    if not (np.isfinite(px) and px > 0):
        raise TiltSeriesError(f"{px_where}: pixel_size_A must be a positive number of Å, got {px:g}")
    if angles_name is not None and not isinstance(angles_name, (str, Path)):  # values, not a file (the Python API)
        angles_path = Path("angles_deg")
        try:
            angles = np.asarray(angles_name, dtype=np.float64)
        except (TypeError, ValueError):
            raise TiltSeriesError(
                f"angles_deg: expected a file name or N numbers (degrees), got {type(angles_name).__name__}"
            ) from None
    elif angles_name is not None:
        angles_path = root / angles_name
        angles = read_angles(angles_path, pick(angles_variable, "angles_variable"))
    elif stack.angles_deg is not None:
        angles_path, angles = proj_path, stack.angles_deg
    else:
        raise TiltSeriesError(f"{where}: 'angles_deg' is missing (give it in {MANIFEST} or as an option)")
    if angles.ndim != 1 and angles.shape[1:] != (3,):
        raise TiltSeriesError(
            f"{angles_path}: expected N single-axis tilt angles (one column) or N x 3 Euler angles, got shape "
            f"{angles.shape}"
        )
    if len(angles) != proj.shape[0]:
        other = [axis for axis in (1, 2) if proj.shape[axis] == len(angles)]
        hint = (
            f"; if the stack holds its tilts along another axis, give tilt_index_axis (--tilt-index-axis, manifest "
            f"key): the stack as read is {proj.shape}"
            if other
            else ""
        )
        raise TiltSeriesError(
            f"{angles_path}: {len(angles)} tilt angles for {proj.shape[0]} projections in {proj_path.name}{hint}"
        )
    given, kept = len(angles), views.kept_views(pick(drop_views, "drop_views"), angles)
    if kept is not None:
        proj, angles = proj[kept], angles[kept]
    truth_name = pick(truth, "truth")
    truth_path = root / truth_name if truth_name is not None else None
    if truth_path is not None and not truth_path.is_file():
        raise TiltSeriesError(f"{truth_path}: truth file not found")
    noise_path = root / manifest["noise"] if "noise" in manifest else None
    if noise_path is not None and not noise_path.is_file():
        raise TiltSeriesError(f"{noise_path}: noise file not found (manifest key noise)")
    axis, axis_angle = pick(tilt_axis, "tilt_axis"), pick(tilt_axis_angle_deg, "tilt_axis_angle_deg")
    if axis_angle is None and stack.imod_tilt_axis_angle_deg is not None:
        axis = axis or "x"  # IMOD measures its angle from Y, the rows: our "x"
        axis_angle = imod_axis_angle(stack.imod_tilt_axis_angle_deg, axis) if axis in TILT_AXES else 0.0
    try:
        return TiltSeries(
            projections=proj,
            angles_deg=angles,
            pixel_size_A=px,
            tilt_axis=axis or "y",
            tilt_axis_angle_deg=axis_angle if axis_angle is not None else 0.0,
            origin_A=manifest.get("origin_A", [0.0, 0.0, 0.0]),
            truth_path=truth_path,
            source=proj_path,
            centre_px=centre_px if centre_px is not None else manifest.get("centre_px"),
            species=pick(species, "species") or (),
            euler_convention=pick(euler_convention, "euler_convention") or "zyz",
            pixel_size_source=px_source,
            view_indices=kept,
            views_given=given,
            noise_path=noise_path,
            contrast=pick(contrast, "contrast") or "adf",
        )
    except TiltSeriesError as exc:
        # Name the file the problem most likely lives in.
        msg = str(exc).split(": ", 1)[-1]
        culprit = (
            angles_path
            if "angle" in msg and "axis" not in msg
            else (where if any(k in msg for k in MANIFEST_WORDS) else proj_path)
        )
        raise TiltSeriesError(f"{culprit}: {msg}") from None


def write_tilt_series(
    out_dir: str | Path,
    projections: np.ndarray,
    angles_deg: np.ndarray,
    pixel_size_A: float,
    truth=None,
    origin_A=(0.0, 0.0, 0.0),
    tilt_axis: str = "y",
    extra: dict | None = None,
    centre_px=None,
    tilt_axis_angle_deg: float = 0.0,
    species=(),
    euler_convention: str = "zyz",
    noise: np.ndarray | None = None,
    contrast: str = "adf",
) -> Path:
    """Write a ``tilt_series.json`` directory; ``truth`` is an AtomSet in its own frame; ``noise``
    the (N, H, W) noise drawn into a replica's ``projections`` (``noise.npy``, manifest key ``noise``).

    The manifest is written last, so a directory with a manifest is complete.
    """
    from gaussian_atoms_method.atoms.atom_set import write_atoms

    series = TiltSeries(
        projections,
        angles_deg,
        pixel_size_A,
        tilt_axis,
        np.asarray(origin_A, dtype=float),
        centre_px=centre_px,
        tilt_axis_angle_deg=tilt_axis_angle_deg,
        species=species,
        euler_convention=euler_convention,
        contrast=contrast,
    )
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / MANIFEST).unlink(missing_ok=True)
    np.save(out / "projections.npy", series.projections)
    np.savetxt(out / "angles.txt", series.orientations_deg, fmt="%.6f")  # Euler angles: phi, theta, psi a row
    manifest = {
        "projections": "projections.npy",
        "angles_deg": "angles.txt",
        "pixel_size_A": series.pixel_size_A,
        "tilt_axis": series.tilt_axis,
        "origin_A": series.origin_A.tolist(),
        "centre_px": series.centre_px.tolist(),
    }
    if series.tilt_axis_angle_deg:
        manifest["tilt_axis_angle_deg"] = series.tilt_axis_angle_deg
    if series.contrast != "adf":
        manifest["contrast"] = series.contrast
    if series.species:
        manifest["species"] = ",".join(series.species)
    if series.euler_deg is not None and series.euler_convention != "zyz":
        manifest["euler_convention"] = series.euler_convention
    if truth is not None:
        write_atoms(truth, out / "atoms_true.xyz")
        manifest["truth"] = "atoms_true.xyz"
    if noise is not None:
        np.save(out / "noise.npy", np.asarray(noise, dtype=np.float32))
        manifest["noise"] = "noise.npy"
    if extra:
        manifest.update(extra)
    write_manifest(out, manifest)
    return out
