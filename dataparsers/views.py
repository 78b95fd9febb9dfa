"""Views that cannot be fitted, named by index and angle, and the views a user leaves out.

Euler angles that move the volume too far from their single-axis tilt for the start
(:func:`start_offset_A`) are refused where the series is read.

A view holding NaN or Inf, or one whose every pixel is the same value (a frame the detector
never read out, a blank left in a stack), carries no projection of the specimen: the first
stops any fit, the second would be fitted as a view in which the specimen is absent.  Both are
named by their index in the file and their tilt angle, with the option that leaves them out
(``drop_views``: ``--drop-views`` on the command line, the manifest key, ``ga.reconstruct``'s
and ``ga.read_tilt_series``' keyword).
"""

from __future__ import annotations

import math

import numpy as np

from gaussian_atoms_method.physics.geometry import detector_axes_from_euler, detector_axes_from_tilts

from .errors import TiltSeriesError

MAX_START_OFFSET_A = 1.0
"""How far (Å) a view with Euler angles may move a point of the fitted volume from where the
single-axis tilt ``theta`` puts it.  The start back-projects about ``theta`` alone; a candidate
that lands less than an atom's projected half width (about 1 Å: an atom's sigma of 0.3-0.8 Å
with the probe's) from its atom is within the fit's reach, and the fit projects with the full
orientation."""


def start_offset_A(
    euler_deg: np.ndarray, image_shape, centre_px, pixel_size_A: float, euler_convention: str = "zyz"
) -> float:
    """The largest detector displacement (Å) between the Euler orientation and the tilt
    ``theta`` alone, over the corners of the volume the fit spans (the detector's field, as
    deep as its longer side)."""
    h, w = (np.asarray(image_shape, dtype=np.float64) - 1) / 2
    half = np.array([h + abs(np.asarray(centre_px)[0] - h), w + abs(np.asarray(centre_px)[1] - w), max(h, w)])
    corners = np.array(np.meshgrid(*[(-x, x) for x in half], indexing="ij")).reshape(3, -1) * pixel_size_A
    exact = detector_axes_from_euler(euler_deg, euler_convention)[:, :2] @ corners
    single = detector_axes_from_tilts(np.asarray(euler_deg)[:, 1], "y")[:, :2] @ corners
    return float(np.abs(exact - single).max())


ANGLE_SUFFIX = "deg"
"""A view to leave out given by its tilt angle ends in this (``-40deg``); a bare integer is the
view's index in the file."""

ANGLE_MATCH_DEG = 0.05
"""A tilt given to leave a view out names the view whose angle lies this close: angle files
give tilts to 0.01-0.1°, and no series steps by less than a degree."""


def named_views(indices, angles_deg, limit: int = 6) -> str:
    """``"3 (12°), 7 (40°)"``: views by their index in the file and their tilt angle, the first
    ``limit`` of them and how many more."""
    shown = [f"{int(i)} ({float(a):g}°)" for i, a in zip(list(indices)[:limit], list(angles_deg)[:limit])]
    more = len(indices) - limit
    return ", ".join(shown) + (f" and {more} more" if more > 0 else "")


def unusable_views(projections: np.ndarray, angles_deg: np.ndarray, indices: np.ndarray, where: str) -> None:
    """Raise :class:`TiltSeriesError` naming the views of the (N, H, W) ``projections`` that hold
    NaN/Inf or are constant, by ``indices`` (their places in the file) and ``angles_deg``."""
    proj = np.asarray(projections)
    finite = np.isfinite(proj).reshape(len(proj), -1)
    bad = np.flatnonzero(~finite.all(axis=1))
    hint = "leave them out with --drop-views {} (drop_views: indices in the file, or tilts as -40deg)"
    if len(bad):
        n_bad = int(np.size(proj) - np.count_nonzero(finite))
        raise TiltSeriesError(
            f"{where}: projections hold {n_bad} NaN/Inf value(s), in view(s) "
            f"{named_views(indices[bad], angles_deg[bad])}; "
            + hint.format(",".join(str(int(i)) for i in indices[bad][:6]))
        )
    flat = proj.reshape(len(proj), -1)
    constant = np.flatnonzero(flat.max(axis=1) == flat.min(axis=1))
    if len(constant) == len(proj):
        said = "all zero" if not np.any(flat[:, 0]) else "constant in every view"
        raise TiltSeriesError(f"{where}: projections are {said}: there is nothing to reconstruct")
    if len(constant):
        values = ", ".join(f"{flat[c, 0]:g}" for c in constant[:6])
        raise TiltSeriesError(
            f"{where}: view(s) {named_views(indices[constant], angles_deg[constant])} hold the same value "
            f"everywhere ({values}): no projection of a specimen; "
            + hint.format(",".join(str(int(i)) for i in indices[constant][:6]))
        )


DETAIL_SMOOTHING_PX = 4.0
"""The local mean :func:`contrast_skew` takes away: a Gaussian of this many pixels, wider than an
atom's image at the 0.2-0.5 Å pixels tomography of atoms uses (sigma 0.3-0.8 Å)."""

DARK_SKEW = -0.1
"""Views whose detail is skewed below this (and by 5 standard errors, ``sqrt(6 / n)`` for n
pixels) hold dark atoms.  Bright atoms are peaks narrower than the gaps between them and skew the
detail positive: +0.19 (54,000-atom Pd, the densest projection we simulate) to +1.3 (a thin Ta
sub-area), the aSi-208 counts +0.9 to +1.1 at every dose; noise alone reads 0 (Poisson counts
above it).  Negated, each reads as far below zero."""


SKEW_PIXELS = 2_000_000
"""The most pixels :func:`contrast_skew` reads (whole views, evenly spread): its standard error
is then 0.002 at most, and a read costs the same at any size of series."""


def contrast_skew(projections: np.ndarray) -> tuple[float, float]:
    """The skewness of the (N, H, W) ``projections``' detail (each view less its local mean,
    :data:`DETAIL_SMOOTHING_PX`; the edges the smoothing pads left out) and its standard error
    under noise: positive where atoms are bright peaks, negative where they are dark dips."""
    from scipy import ndimage

    proj = np.asarray(projections)
    proj = np.asarray(proj[:: max(1, int(np.ceil(proj.size / SKEW_PIXELS)))], dtype=np.float64)  # views evenly spread
    detail = proj - ndimage.gaussian_filter(proj, (0, DETAIL_SMOOTHING_PX, DETAIL_SMOOTHING_PX), mode="nearest")
    edge = int(2 * DETAIL_SMOOTHING_PX)
    if min(proj.shape[1:]) > 4 * edge:
        detail = detail[:, edge:-edge, edge:-edge]
    d = detail.ravel() - detail.mean()
    spread = float(np.mean(d**2))
    skew = float(np.mean(d**3) / spread**1.5) if spread > 0 else 0.0
    return skew, float(np.sqrt(6.0 / d.size))


def dark_atoms(projections: np.ndarray, where: str) -> None:
    """Raise :class:`TiltSeriesError` where the views' atoms are dark on a brighter background
    (:func:`contrast_skew` below :data:`DARK_SKEW` by 5 standard errors): bright-field images, or
    a stack saved inverted.  The fit's forward model is the projected potential (or ADF-STEM's
    signal, which grows with it): atoms bright."""
    skew, error = contrast_skew(projections)
    if skew < DARK_SKEW and skew < -5 * error:
        raise TiltSeriesError(
            f"{where}: the views' atoms look dark on a brighter background (their detail about each view's local "
            f"mean is skewed {skew:+.2f}; bright atoms skew it +0.2 to +1.3), as bright-field images are: the fit "
            f"needs atoms bright (ADF-STEM, the projected potential); negate the stack (max - views) if it was "
            f"saved inverted"
        )


ATOM_SIGMA_A = (0.1, 1.0)
"""The atoms' image widths (sigma, Å, as :func:`atom_image_sigma_px` reads them) a series of
atoms can hold: it reads 0.30-0.40 Å on every series here at its true pixel size (the demo, four
Ta sub-areas and a replica, 2,000- to 76,000-atom Pd, the aSi-208 counts), and below the true
width (0.37 for atoms 0.61 Å wide, potential and blur).  Above 1 Å no probe separates atoms
2.5 Å apart; below 0.1 Å lies under the projected potential's own core."""

STRUCTURE_SHARE = 0.1
"""The views' detail must hold at least this share of its variance in the correlation between
neighbouring pixels for an atom's width to be read from it (white noise holds none; the
aSi-208 counts at their two lower doses hold 0.01-0.04 and are not judged)."""


def atom_image_sigma_px(projections: np.ndarray) -> float:
    """The width (Gaussian sigma, pixels) of the blobs the (N, H, W) ``projections`` hold, from
    the detail's autocorrelation at one and two pixels (for Gaussian blobs of sigma s it falls
    as ``exp(-r^2 / 4 s^2)``; white noise adds nothing there), on eight views; NaN where the
    detail holds too little structure (:data:`STRUCTURE_SHARE`)."""
    from scipy import ndimage

    proj = np.asarray(projections)
    proj = np.asarray(proj[:: max(1, len(proj) // 8)], dtype=np.float64)
    edge = int(3 * DETAIL_SMOOTHING_PX)
    if min(proj.shape[1:]) <= 4 * edge:
        return float("nan")
    detail = proj - ndimage.gaussian_filter(
        proj, (0, 1.5 * DETAIL_SMOOTHING_PX, 1.5 * DETAIL_SMOOTHING_PX), mode="nearest"
    )
    d = detail[:, edge:-edge, edge:-edge]
    d = d - d.mean()
    c0 = float(np.mean(d * d))
    c1, c2 = (0.5 * float(np.mean(d[:, :, :-r] * d[:, :, r:]) + np.mean(d[:, :-r, :] * d[:, r:, :])) for r in (1, 2))
    if not (c0 > 0 and c1 >= STRUCTURE_SHARE * c0 and 0 < c2 < c1):
        return float("nan")
    return float(np.sqrt(3.0 / (4.0 * np.log(c1 / c2))))


def implausible_pixel_size(projections: np.ndarray, pixel_size_A: float, where: str, source: str = "") -> None:
    """Raise :class:`TiltSeriesError` where ``pixel_size_A`` cannot be right: whatever the views
    hold, where a pixel is wider than an atom's image can be (twice the widest, :data:`ATOM_SIGMA_A`:
    every atom within one pixel) or the field narrower than the narrowest (four of its sigma: no
    atom fits); and where the views' structure says it (:func:`atom_image_sigma_px`), where it puts
    the atoms at widths no atom's image has, with the factor it looks off by against the width the
    measure reads on real and simulated series (0.35 Å)."""
    low, high = ATOM_SIGMA_A
    named = f"{where}: pixel_size_A {pixel_size_A:g} Å{f' (from {source})' if source else ''}"
    field_A = min(np.shape(projections)[1:]) * pixel_size_A
    if pixel_size_A > 2 * high:
        raise TiltSeriesError(
            f"{named} is wider than any atom's image (sigma at most {high:g} Å): every atom would fall within one "
            f"pixel; atomic tomography samples at 0.2-0.5 Å"
        )
    if field_A < 4 * low:
        raise TiltSeriesError(
            f"{named} makes the views {field_A:.3g} Å across, narrower than one atom's image ({4 * low:g} Å at the "
            f"least); atomic tomography samples at 0.2-0.5 Å"
        )
    sigma_A = atom_image_sigma_px(projections) * pixel_size_A
    if not np.isfinite(sigma_A) or low <= sigma_A <= high:
        return
    factor = sigma_A / 0.35
    off = f"about {factor:.1f} times too large" if factor > 1 else f"about {1 / factor:.1f} times too small"
    raise TiltSeriesError(
        f"{named} makes the atoms' images {sigma_A:.2f} Å wide (sigma), where atoms image at {low:g}-{high:g} Å: "
        f"the pixel size looks {off}"
    )


def views_to_drop(spec, angles_deg: np.ndarray, where: str = "drop_views") -> np.ndarray:
    """(K,) the indices of the views ``spec`` names: a string of comma-separated indices in the
    file (``"3,7"``) and tilts ending in ``deg`` (``"-40deg"``, the view within
    :data:`ANGLE_MATCH_DEG` of it), or a sequence of such items.  Raises :class:`TiltSeriesError`
    for an item that names no view."""
    if spec is None:
        return np.zeros(0, dtype=np.int64)
    items = [s.strip() for s in spec.split(",")] if isinstance(spec, str) else [str(s).strip() for s in spec]
    angles = np.asarray(angles_deg, dtype=np.float64)
    out = []
    for item in filter(None, items):
        try:
            value = float(item[: -len(ANGLE_SUFFIX)]) if item.endswith(ANGLE_SUFFIX) else int(item)
        except ValueError:
            raise TiltSeriesError(
                f"{where}: expected view indices (3,7) or tilts ending in {ANGLE_SUFFIX} (-40deg), got {item!r}"
            ) from None
        if isinstance(value, float):
            nearest = int(np.argmin(np.abs(angles - value)))
            if abs(angles[nearest] - value) > ANGLE_MATCH_DEG:
                raise TiltSeriesError(
                    f"{where}: no view at {value:g}° (the nearest is {nearest} at {angles[nearest]:g}°)"
                )
            out.append(nearest)
        elif 0 <= value < len(angles):
            out.append(value)
        else:
            raise TiltSeriesError(f"{where}: view {value} is not among the {len(angles)} views (0-{len(angles) - 1})")
    return np.unique(np.asarray(out, dtype=np.int64))


def kept_views(spec, angles_deg: np.ndarray) -> np.ndarray | None:
    """(K,) the indices of the views ``spec`` leaves in (:func:`views_to_drop`), of the (N,) tilts
    or (N, 3) Euler angles ``angles_deg`` (their tilt the middle column); None without ``spec``
    (every view)."""
    if spec is None:
        return None
    angles = np.asarray(angles_deg, dtype=np.float64)
    return np.setdiff1d(np.arange(len(angles)), views_to_drop(spec, angles[:, 1] if angles.ndim == 2 else angles))


def views_of(series, indices):
    """The :class:`~dataparsers.tilt_series_format.TiltSeries` of ``series``' views at (K,)
    ``indices`` (of its views), their angles and indices in the file with them."""
    import dataclasses

    kept = np.asarray(indices, dtype=np.int64)
    euler = None if series.euler_deg is None else series.euler_deg[kept]
    return dataclasses.replace(
        series,
        projections=series.projections[kept],
        angles_deg=series.angles_deg[kept],
        euler_deg=euler,
        view_indices=series.view_indices[kept],
    )


MIN_DIRECTIONS = 3
"""The fewest directions (tilt angles modulo 180 deg) a series is fitted from.  Two projections
cannot fix atoms in 3D: any two atoms of a slice and the other two corners of the parallelogram
the two directions draw through them project the same (discrete tomography's switching
component), and a two-view series fitted anyway put 1.19 false atoms per true one."""

MIN_SPAN_DEG = 5.0
"""Tilt angles spanning less than this tell no depth (two atoms 2 Å apart along the beam move by
2 Å x sin(5 deg) = 0.17 Å between the extreme views, under any pixel): refused, and where the
same numbers read as radians span more, said to be radians."""


def undecidable_depth(angles: np.ndarray, where: str) -> None:
    """Raise :class:`TiltSeriesError` where the tilts (degrees) cannot fix an atom in 3D: fewer
    than :data:`MIN_DIRECTIONS` directions, or a span under :data:`MIN_SPAN_DEG` (said to be
    radians where, read so, they would span more)."""
    directions = np.unique(np.round(np.mod(angles, 180.0), 6) % 180.0)
    if len(directions) < MIN_DIRECTIONS:
        seen = f"{len(angles)} projection{'' if len(angles) == 1 else 's'} from {len(directions)} direction"
        raise TiltSeriesError(
            f"{where}: {seen}{'' if len(directions) == 1 else 's'}: at least {MIN_DIRECTIONS} are needed to fix "
            f"an atom in 3D (from two, any two atoms of a slice can trade places with the other two corners of "
            f"their parallelogram and project the same)"
        )
    span = float(angles.max() - angles.min())
    if span < MIN_SPAN_DEG and np.max(np.abs(angles)) <= 0.5 * math.pi and math.degrees(span) >= MIN_SPAN_DEG:
        raise TiltSeriesError(
            f"{where}: the tilt angles span only {span:.3g} deg ({angles.min():.3g} to {angles.max():.3g}); as "
            f"radians they would span {math.degrees(span):.0f} deg: give the angles in degrees"
        )
    if span < MIN_SPAN_DEG:
        raise TiltSeriesError(
            f"{where}: the tilt angles span only {span:.3g} deg ({angles.min():.3g} to {angles.max():.3g}): two "
            f"atoms 2 Å apart along the beam move by under {2 * math.sin(math.radians(MIN_SPAN_DEG)):.2f} Å "
            f"between the views, which tells no depth; at least {MIN_SPAN_DEG:g} deg are needed"
        )
