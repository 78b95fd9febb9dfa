"""A run's per-view registration as a file: ``registration.csv``.

One row per view, in the series' order: ``view`` (its index), ``shift_rows_px`` and
``shift_cols_px`` (how far the view's content sits shifted on the detector, pixels, the shifts
a translation of the object makes taken out) and ``gain`` (the view's intensity against the
views' mean).  A fit that learns shifts or gains writes it; ``gaussian-atoms simulate --like DIR
--shifts-from FILE`` puts the same misregistration into a replica.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

COLUMNS = ("view", "shift_rows_px", "shift_cols_px", "gain")


def write_registration(path: Path, shifts_px: np.ndarray, gains: np.ndarray) -> None:
    """Write each view's shift ((V, 2) rows, columns; pixels) and gain ((V,)) to ``path``.

    >>> import tempfile
    >>> p = Path(tempfile.mkdtemp()) / "registration.csv"
    >>> write_registration(p, np.array([[0.5, -0.25], [0.0, 1.0]]), np.array([1.0, 0.97]))
    >>> shifts, gains = read_registration(p)
    >>> shifts.tolist(), gains.tolist()
    ([[0.5, -0.25], [0.0, 1.0]], [1.0, 0.97])
    """
    shifts = np.asarray(shifts_px, dtype=np.float64).reshape(-1, 2)
    gains = np.asarray(gains, dtype=np.float64).reshape(len(shifts))
    with open(path, "w", newline="") as f:
        out = csv.writer(f)
        out.writerow(COLUMNS)
        for view, ((rows, cols), gain) in enumerate(zip(shifts, gains)):
            out.writerow((view, f"{rows:.6g}", f"{cols:.6g}", f"{gain:.6g}"))


def read_registration(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Each view's shift ((V, 2) pixels) and gain ((V,)) from a file :func:`write_registration`
    wrote; a ``ValueError`` naming the file where it is not one (its columns, its views in order,
    finite numbers)."""
    path = Path(path)
    try:
        with open(path, newline="") as f:
            rows = list(csv.reader(f))
    except OSError as err:
        raise ValueError(f"{path}: cannot read it ({err.strerror or err})") from None
    if not rows or tuple(name.strip() for name in rows[0]) != COLUMNS:
        raise ValueError(f"{path}: expected a registration.csv with the columns {', '.join(COLUMNS)}")
    try:
        table = np.array([[float(x) for x in row] for row in rows[1:] if row], dtype=np.float64).reshape(-1, 4)
    except ValueError:
        raise ValueError(f"{path}: expected numbers in every row under {', '.join(COLUMNS)}") from None
    if not len(table) or not np.array_equal(table[:, 0], np.arange(len(table))) or not np.isfinite(table).all():
        raise ValueError(f"{path}: expected one row per view, numbered 0, 1, 2, ... in order, with finite values")
    return table[:, 1:3], table[:, 3]
