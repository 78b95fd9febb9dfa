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
    depth_rise: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The statement widened by ``floor_A`` (3,) Å along x, y, z, in quadrature: each atom's
    (N, 3) precision, its 95% depth half-width (N,) (along the beam: the floor along z), and its
    depth flag (N,) raised where the widened interval exceeds half the hard core
    (:func:`wider_than_half_core`) or, given ``depth_rise`` (N,), where another place along the
    beam comes within the widened interval's reach (:func:`another_place_within`).

    >>> std, half, flag = with_floor(np.full((1, 3), 0.03), np.array([0.1]), np.array([False]), (0.04, 0.0, 0.4), 1.6)
    >>> std.round(3).tolist(), half.round(3).tolist(), flag.tolist()
    ([[0.05, 0.03, 0.401]], [0.79], [True])
    """
    floor = np.asarray(floor_A, dtype=np.float64).reshape(3)
    std = np.sqrt(np.asarray(position_std_A, dtype=np.float64) ** 2 + floor**2)
    stated = np.asarray(depth_halfwidth_A, dtype=np.float64)
    half = np.sqrt(stated**2 + (Z95 * floor[2]) ** 2)
    flag = np.asarray(depth_open, dtype=bool) | wider_than_half_core(half, hard_core_A)
    if depth_rise is not None:
        flag |= another_place_within(depth_rise, stated, half)
    return std, half, flag


def another_place_within(depth_rise: np.ndarray, stated_halfwidth_A: np.ndarray, halfwidth_A: np.ndarray) -> np.ndarray:
    """(N,) bool: the best other place the depth profile tried (``depth_rise`` (N,), the cost's
    least rise there in the atom's stated variance, :attr:`.evidence.AtomEvidence.depth_rise`) lies within
    the 95% interval once the floor has widened it from ``stated_halfwidth_A`` to ``halfwidth_A``
    (N,).

    Why: the floor says the stated variance understates each atom's error variance by the ratio
    ``(halfwidth / stated)^2`` (a bias alike in every view, which no residual shows).  The
    profile's rise is a misfit of the same views, so it is read in the same widened unit: another
    place is as good as the atom's own where its rise is under ``Z95^2`` times that ratio.  On the
    54,000-atom Pd particle through ADF physics, the false atoms' least rise had a median of 7
    noise variances and the right atoms' 90.  NaN (no profile, or one not known) opens nothing.

    >>> another_place_within(np.array([7.0, 90.0, np.nan]), np.full(3, 0.05), np.full(3, 0.12)).tolist()
    [True, False, False]
    """
    ratio = (np.asarray(halfwidth_A, dtype=np.float64) / np.asarray(stated_halfwidth_A, dtype=np.float64)) ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.asarray(depth_rise, dtype=np.float64) < Z95**2 * ratio


MIN_WIDTH_REFERENCE = 10
"""An element's median width is its own reference where it has at least this many atoms (the
median of fewer scatters by more than a third of one atom's spread); else all atoms' median."""


def wider_than_one_atom(sigmas_A, width_std_A, level: float, species=None) -> np.ndarray:
    """(N,) bool: the atom is wider than one atom of its element by more than ``level`` times its
    width's precision: ``sigma_i - median > level * width_std_i``, the median over the atoms of
    the same element (all atoms for one element, none given, or an element with fewer than
    :data:`MIN_WIDTH_REFERENCE`).

    Why: through one microscope every atom of an element is imaged alike (the probe's blur
    dominates its width), so a single atom's fitted width scatters about the element's by its
    precision alone.  A Gaussian that holds two unparted atoms, or one atom and a neighbour's
    tail, is wider.  ``level`` is the proof level (:func:`.evidence.proof_level`): by chance
    no single atom among as many reaches it, with the same family-wise error as a proof.  On a
    2,000-atom Ni-Pd-Pt particle through ADF physics, fitted without the split by width
    (:func:`~gaussian_atoms_method.density.parameters.split_width`), every false atom lay 4.8-9.7
    precisions above its element's width, 23 of the 29 Ni atoms named Pd beyond the level, and
    2% of the right atoms.  NaN precisions are not open.

    >>> wider_than_one_atom(np.array([0.58, 0.59, 0.57, 0.80]), np.full(4, 0.02), 4.0).tolist()
    [False, False, False, True]
    """
    sigmas = np.asarray(sigmas_A, dtype=np.float64)
    std = np.asarray(width_std_A, dtype=np.float64)
    reference = np.full(sigmas.shape, np.median(sigmas) if len(sigmas) else np.nan)
    if species is not None:
        species = np.asarray(species)
        for element in np.unique(species):
            mine = species == element
            if mine.sum() >= MIN_WIDTH_REFERENCE:
                reference[mine] = np.median(sigmas[mine])
    with np.errstate(invalid="ignore"):
        return sigmas - reference > level * std
