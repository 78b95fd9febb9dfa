"""A catalogue of broken and odd tilt series, as users bring them.

Each case writes a tilt-series directory; a broken one must stop with one line naming the file
or option (exit 2, no traceback, nothing written), an odd but valid one must train.  Used by
``tests/test_front_door.py`` and ``gaussian-atoms input-matrix`` (:mod:`.input_matrix`) (which runs every case through
``ns-train gaussian-atoms`` and ``gaussian-atoms train``).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

import numpy as np

from dataparsers.tilt_series_format import MANIFEST, write_tilt_series
from gaussian_atoms_method.atoms.atom_set import AtomSet


def valid_series(out: Path, shape=(24, 24), n_views=7, dtype=np.float32, **kw) -> Path:
    """A small valid tilt series in ``out``: (n_views, *shape) uniform noise of ``dtype``
    (integers scaled to 0-1000 counts), tilts -60..60 deg, 0.3 Å pixels, two Au atoms as the
    truth; ``kw`` goes to :func:`write_tilt_series` (tilt_axis, centre_px, ...)."""
    rng = np.random.default_rng(0)
    projections = (rng.uniform(0, 1, (n_views,) + shape) * (1000 if np.issubdtype(dtype, np.integer) else 1)).astype(
        dtype
    )
    angles = np.linspace(-60, 60, n_views)
    truth = AtomSet(np.array([[0.0, 0.0, 0.0], [2.5, 0.0, 0.0]]), species=["Au", "Au"])
    out = write_tilt_series(out, projections, angles, 0.3, truth=truth, **kw)
    np.save(out / "projections.npy", projections)  # as given: write_tilt_series stores float32
    return out


def edit_manifest(out: Path, **changes) -> Path:
    """Set manifest keys of the series in ``out`` (None removes the key)."""
    manifest = json.loads((out / MANIFEST).read_text())
    for key, value in changes.items():
        if value is None:
            manifest.pop(key, None)
        else:
            manifest[key] = value
    (out / MANIFEST).write_text(json.dumps(manifest))
    return out


def resave(out: Path, transform: Callable[[np.ndarray], np.ndarray]) -> Path:
    """Replace the projections of the series in ``out`` by ``transform`` of them."""
    np.save(out / "projections.npy", transform(np.load(out / "projections.npy")))
    return out


def valid_then(out: Path, change: Callable[[Path], object]) -> Path:
    """A valid series in ``out``, then ``change(out)`` applied to its files."""
    change(valid_series(out))
    return out


def _atoms(p, sign: float = 1.0, n: int = 6):
    """Each view ``n`` atoms (2D Gaussians of 1.2 px, height 40) on a floor of 100 with noise of
    1: bright, or dark (``sign`` -1) as a bright field shows them."""
    rng = np.random.default_rng(1)
    r, c = np.meshgrid(np.arange(p.shape[1]), np.arange(p.shape[2]), indexing="ij")
    out = 100.0 + rng.normal(0.0, 1.0, p.shape)
    for view in out:
        for y, x in rng.uniform(3, min(p.shape[1:]) - 3, (n, 2)):
            view += sign * 40.0 * np.exp(-((r - y) ** 2 + (c - x) ** 2) / (2 * 1.2**2))
    return out.astype(p.dtype)


def _dark_atoms(p):
    return _atoms(p, -1.0)


def _empty_view(p):
    p = p.copy()
    p[4] = 0
    return p


def _nan(p):
    p = p.copy()
    p[2, 3, 4] = np.nan
    return p


BROKEN: dict[str, tuple[Callable[[Path], Path], str]] = {
    # name: (writer, a fragment the one-line message must hold)
    "missing directory": (lambda out: out / "nowhere", "data directory not found"),
    "no manifest": (
        lambda out: valid_then(out, lambda d: (d / MANIFEST).unlink()),
        "not found, and no projections option",
    ),
    "bad JSON": (
        lambda out: valid_then(out, lambda d: (d / MANIFEST).write_text("{projections: oops")),
        "not valid JSON",
    ),
    "manifest not an object": (
        lambda out: valid_then(out, lambda d: (d / MANIFEST).write_text("[1, 2]")),
        "expected a JSON object",
    ),
    "unknown key": (lambda out: edit_manifest(valid_series(out), pixelsize=0.3), "unknown key"),
    "projections missing": (
        lambda out: edit_manifest(valid_series(out), projections="gone.npy"),
        "gone.npy: projections file not found",
    ),
    "angles missing": (
        lambda out: edit_manifest(valid_series(out), angles_deg="gone.txt"),
        "gone.txt: tilt angles file not found",
    ),
    "no pixel size": (lambda out: edit_manifest(valid_series(out), pixel_size_A=None), "'pixel_size_A' is missing"),
    "negative pixel size": (
        lambda out: edit_manifest(valid_series(out), pixel_size_A=-0.3),
        "pixel_size_A must be a positive",
    ),
    "pixel size not a number": (
        lambda out: edit_manifest(valid_series(out), pixel_size_A="big"),
        "pixel_size_A must be a number",
    ),
    "wrong angle count": (
        lambda out: valid_then(out, lambda d: (d / "angles.txt").write_text("0\n10\n20\n")),
        "3 tilt angles for 7 projections",
    ),
    "duplicate angles": (
        lambda out: valid_then(
            out, lambda d: (d / "angles.txt").write_text("\n".join(["0", "0", "10", "20", "30", "40", "50"]))
        ),
        "duplicate tilt angle",
    ),
    "angles not numbers": (
        lambda out: valid_then(out, lambda d: (d / "angles.txt").write_text("a\nb\n")),
        "could not read tilt angles",
    ),
    "NaN pixels": (lambda out: resave(valid_series(out), _nan), "NaN/Inf value(s), in view(s) 2 (-20°)"),
    "an empty view": (lambda out: resave(valid_series(out), _empty_view), "view(s) 4 (20°) hold the same value"),
    "dark atoms": (lambda out: resave(valid_series(out), _dark_atoms), "atoms look dark on a brighter background"),
    "pixel size 4 times too large": (
        lambda out: edit_manifest(
            resave(valid_series(out, shape=(64, 64)), lambda p: _atoms(p, n=40)), pixel_size_A=1.2
        ),
        "the pixel size looks about",
    ),
    "2D projections": (lambda out: resave(valid_series(out), lambda p: p[0]), "3D stack"),
    "complex projections": (lambda out: resave(valid_series(out), lambda p: p.astype(np.complex64)), "real numbers"),
    "unknown tilt axis": (lambda out: edit_manifest(valid_series(out), tilt_axis="z"), "tilt_axis must be one of"),
    "bad centre": (lambda out: edit_manifest(valid_series(out), centre_px=[1, 2, 3]), "centre_px must be two"),
    "bad origin": (lambda out: edit_manifest(valid_series(out), origin_A=[0, 0]), "origin_A must be three"),
    "truth missing": (lambda out: edit_manifest(valid_series(out), truth="gone.xyz"), "gone.xyz: truth file not found"),
    "truth unreadable": (
        lambda out: valid_then(out, lambda d: (d / "atoms_true.xyz").write_text("not an xyz file\n")),
        "atoms_true.xyz",
    ),
    "single projection": (
        lambda out: valid_then(out, lambda d: (resave(d, lambda p: p[:1]), (d / "angles.txt").write_text("0\n"))),
        "1 projection from 1 direction: at least 3 are needed",
    ),
    "all at one direction": (
        lambda out: valid_then(out, lambda d: (resave(d, lambda p: p[:2]), (d / "angles.txt").write_text("-90\n90\n"))),
        "2 projections from 1 direction: at least 3 are needed",
    ),
    "two directions": (
        lambda out: valid_then(out, lambda d: (resave(d, lambda p: p[:2]), (d / "angles.txt").write_text("-60\n60\n"))),
        "2 projections from 2 directions: at least 3 are needed",
    ),
    "all zero": (lambda out: resave(valid_series(out), lambda p: np.zeros_like(p)), "all zero"),
    "angles in radians": (
        lambda out: valid_then(
            out,
            lambda d: (d / "angles.txt").write_text("\n".join(f"{a:.4f}" for a in np.radians(np.linspace(-60, 60, 7)))),
        ),
        "give the angles in degrees",
    ),
    "tilt axis last": (
        lambda out: resave(valid_series(out, shape=(24, 20)), lambda p: np.moveaxis(p, 0, 2)),
        "give tilt_index_axis",
    ),
    "1 x 1 projections": (lambda out: resave(valid_series(out), lambda p: p[:, :1, :1]), "at least 5 x 5"),
    "zero pixel size": (
        lambda out: edit_manifest(valid_series(out), pixel_size_A=0),
        "pixel_size_A must be a positive",
    ),
    "unknown species": (lambda out: edit_manifest(valid_series(out), species="Ta,Xx"), "unknown element 'Xx'"),
}

ODD: dict[str, Callable[[Path], Path]] = {
    "integer counts": lambda out: valid_series(out, dtype=np.uint16),
    "non-square images": lambda out: valid_series(out, shape=(20, 31)),
    "negative values": lambda out: resave(valid_series(out), lambda p: p - 0.5),
    "x tilt axis": lambda out: valid_series(out, tilt_axis="x"),
    "tilt axis at -86 deg in the image": lambda out: valid_series(out, tilt_axis_angle_deg=-86.0),
    "off-centre tilt axis": lambda out: valid_series(out, centre_px=(10.0, 13.5)),
    "species given": lambda out: valid_series(out, species="Au"),
}


def own_lines(text: str) -> list[str]:
    """Lines of a launcher's output as a terminal shows them (a progress bar's redrawings after
    carriage returns are one line, and a nested bar's drawings before its last, each followed by a
    cursor-up, are the line below it) less the FutureWarnings torch and nerfstudio print on import
    (each a "...Warning: ..." line and the indented source line under it): what the one-line rule
    for bad input and the console's length are about."""
    lines, skip = [], False
    for physical in text.split("\n"):
        # A progress bar redraws its line after each carriage return: a terminal shows the last drawing.
        line = next((part for part in reversed(physical.split("\r")) if part.strip()), "")
        if "\x1b[A" in line:  # a nested bar drawn below, the cursor moved back up: redrawn in place
            continue
        if "Warning: " in line:
            skip = True
            continue
        if skip and line.startswith(" "):
            continue
        skip = False
        if line.strip():
            lines.append(line)
    return lines
