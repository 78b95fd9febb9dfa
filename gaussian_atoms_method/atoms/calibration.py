"""A precision calibrated against actual errors: the floor a replica measures, and the statement
it widens.

Each atom's stated precision (:mod:`.evidence`: the sandwich over the views, neighbours re-fitted)
holds what differs from view to view: noise, a view's misregistration, the support under it.
What is the same in every view stays outside it: a bias that the forward model makes alike in
each projection (a probe's tails over a neighbour, an atom's shape, a support's texture at the
atom). No fit can see that bias in its own residual; a replica of the experiment can
(``gaussian-atoms simulate --like``): its errors against its truth, beside the precision its run
stated, give the error the statement does not hold (:func:`precision_floor_A`). A run
of the real series given that floor (``precision_floor_A``) adds it in quadrature to each
atom's statement (:func:`with_floor`).
"""

from __future__ import annotations

import numpy as np

Z95 = 1.959963984540054
"""The normal distribution's two-sided 95% quantile: a 95% interval's half-width in standard
deviations."""


def precision_floor_A(error_A: np.ndarray, stated_std_A: np.ndarray, coverage: float = 0.95) -> np.ndarray:
    """(3,) the error along x, y, z (Å) that the stated precision does not hold: the least floor
    ``f`` whose quadrature sum with each statement, ``sqrt(std^2 + f^2)``, brings ``coverage`` of
    the errors inside their ``Z95``-wide intervals (zero where the statement holds them already).

    ``error_A`` (N, 3) the found atoms' errors against a truth, after the global shift;
    ``stated_std_A`` (N, 3) the precision their run stated.  Each atom needs
    ``f_i = sqrt(max(0, (e_i / Z95)^2 - std_i^2))``; the floor is their ``coverage`` quantile.  If
    the errors are the stated scatter plus a bias of variance ``f^2`` the same for every atom,
    this reads ``f``.  A quantile, not a mean square: the atoms a run leaves open state wide
    intervals, and their variances would hide what the others miss.

    >>> error = np.array([[0.03, 0.0, 0.05], [-0.02, 0.0, -0.05]])
    >>> precision_floor_A(error, np.full((2, 3), 0.01), coverage=0.5).round(4).tolist()
    [0.0068, 0.0, 0.0235]
    """
    error_A, stated_std_A = np.asarray(error_A, dtype=np.float64), np.asarray(stated_std_A, dtype=np.float64)
    ok = np.all(np.isfinite(stated_std_A), axis=1)
    if not ok.any():
        return np.zeros(3)
    needed = np.sqrt(np.clip((error_A[ok] / Z95) ** 2 - stated_std_A[ok] ** 2, 0.0, None))
    return np.quantile(needed, coverage, axis=0)


def wider_than_half_core(depth_halfwidth_A: np.ndarray, hard_core_A: float | None) -> np.ndarray:
    """(N,) bool: the 95% depth interval (half-widths (N,), Å) is wider than half the hard core,
    so two atoms could trade places along it: the ``depth_open`` flag of :mod:`.evidence`.  All
    False where the hard core is unknown (None or infinite); NaN half-widths are not open."""
    half = np.asarray(depth_halfwidth_A, dtype=np.float64)
    if hard_core_A is None or not np.isfinite(hard_core_A):
        return np.zeros(half.shape, bool)
    with np.errstate(invalid="ignore"):
        return 2 * half > 0.5 * hard_core_A


def with_floor(
    position_std_A: np.ndarray,
    depth_halfwidth_A: np.ndarray,
    depth_open: np.ndarray,
    floor_A,
    hard_core_A: float | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The statement widened by ``floor_A`` (3,) Å along x, y, z, in quadrature: each atom's
    (N, 3) precision, its 95% depth half-width (N,) (along the beam: the floor along z), and its
    depth flag (N,) raised where the widened interval exceeds half the hard core
    (:func:`wider_than_half_core`).

    >>> std, half, flag = with_floor(np.full((1, 3), 0.03), np.array([0.1]), np.array([False]), (0.04, 0.0, 0.4), 1.6)
    >>> std.round(3).tolist(), half.round(3).tolist(), flag.tolist()
    ([[0.05, 0.03, 0.401]], [0.79], [True])
    """
    floor = np.asarray(floor_A, dtype=np.float64).reshape(3)
    std = np.sqrt(np.asarray(position_std_A, dtype=np.float64) ** 2 + floor**2)
    half = np.sqrt(np.asarray(depth_halfwidth_A, dtype=np.float64) ** 2 + (Z95 * floor[2]) ** 2)
    return std, half, np.asarray(depth_open, dtype=bool) | wider_than_half_core(half, hard_core_A)
