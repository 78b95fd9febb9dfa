"""Atoms of overlapping sub-area fits joined into one film, each with the evidence of the overlap.

Every sub-area's fit reports atoms in its own frame; moved into the film's frame by the
sub-area's offset, the reports of one atom from the sub-areas that see it lie close together.

* **Joined.** Two reports from different sub-areas are one atom when each is the other's
  nearest report in the other sub-area and they lie closer than half the material's hard core
  (:mod:`gaussian_atoms_method.atoms.hard_core`): two distinct atoms are never closer than the
  hard core, so two reports of distinct atoms are never both nearer than half of it to one
  point.  Joined reports (transitively, at most one per sub-area) are one atom at their mean.
* **Counted.** ``found_in``: the sub-areas that reported it; ``covered_by``: the sub-areas whose
  interior (the detector less its edges, whose atoms only some views see) holds it.  Only a
  sub-area's interior reports are used.
* **Confirmed.** A run's artefact recurs in another run at some low rate, a real atom at a
  high one.  The two rates are read from the film itself: ``found_in`` out of ``covered_by``
  as a mixture of two binomials, fitted by expectation-maximisation; an atom is confirmed
  where the real component is the more probable; the rest are reported as non-atoms.  Where
  the two rates do not separate (within :data:`SAME_RATE` of each other: too few fits cover
  each atom, or the film shows no artefacts to tell real atoms by) the overlap confirms
  nothing: every joined atom is reported, none confirmed by it.
* **Agreement.** Two overlapping fits judge each other without a truth (:func:`pair_agreement`):
  of the atoms one reports in their common interior, the share the other reports too (the
  mutual nearest within half the hard core, as joined), each way; and where they state their
  precision, how far apart they place the atoms both report, against what their precisions
  allow.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from gaussian_atoms_method.atoms.calibration import Z95

SAME_RATE = 0.1
"""Rates closer than this are one population: with seven fits covering an atom, one more or one
fewer finding it moves its share by 0.14."""


@dataclass
class Reports:
    """One sub-area's atoms in the film's frame: ``positions`` (N, 3) Å and the sub-area's
    interior, ``interior_A`` (2, 2): the lower and upper (x, y) corners in the film's frame;
    optionally each atom's stated precision, ``position_std_A`` (N, 3) Å (``atoms.csv``'s
    ``std_x_A``, ``std_y_A``, ``std_z_A``), and whether its fit trusts it, ``trusted`` (N,) bool
    (``atoms.csv``'s ``trusted``)."""

    name: str
    positions: np.ndarray
    interior_A: np.ndarray
    position_std_A: np.ndarray | None = None
    trusted: np.ndarray | None = None

    def inside(self, positions: np.ndarray) -> np.ndarray:
        """(M,) whether each of ``positions`` (M, 3) lies in this sub-area's interior (x, y)."""
        xy = np.asarray(positions, dtype=np.float64).reshape(-1, 3)[:, :2]
        return np.all((xy >= self.interior_A[0]) & (xy <= self.interior_A[1]), axis=1)


@dataclass
class FilmAtoms:
    """The joined atoms: ``positions`` (M, 3) Å in the film's frame, ``found_in`` and
    ``covered_by`` (M,) counts, ``confirmed`` (M,) bool, the two recurrence rates read
    (``rate_real``, ``rate_artefact``) and whether they separate (else no atom is confirmed by
    the overlap, and every one is reported); ``spread_A`` (M, 3): the standard deviation along
    x, y, z of the fits' reports of each atom about their mean (NaN where one fit found it),
    each atom's precision as the overlapping fits show it, without a truth; ``trusted_in`` (M,):
    how many of the fits that found it trust it (None where the reports do not say)."""

    positions: np.ndarray
    found_in: np.ndarray
    covered_by: np.ndarray
    confirmed: np.ndarray
    rate_real: float
    rate_artefact: float
    spread_A: np.ndarray | None = None
    trusted_in: np.ndarray | None = None

    @property
    def separated(self) -> bool:
        """Whether the two recurrence rates tell real atoms from artefacts (:func:`rates_separate`)."""
        return rates_separate(self.rate_real, self.rate_artefact)

    @property
    def reported(self) -> np.ndarray:
        """(M,) the atoms reported: the confirmed ones, or all where the overlap cannot tell."""
        return self.confirmed if self.separated else np.ones(len(self.confirmed), dtype=bool)

    @property
    def trusted(self) -> np.ndarray | None:
        """(M,) the reported atoms a majority of the fits that found them trust (None where the
        reports do not say): one fit's trust (proven, closed in depth, one atom wide) is read
        from its own views, whose errors the overlapping fits do not all share.  On the Ta film's
        second strip (13 sub-areas, unregistered) 0.92 of these lay on an atom of the authors'
        model, against 0.82 of all reported."""
        if self.trusted_in is None:
            return None
        return self.reported & (2 * self.trusted_in > self.found_in)


def join_reports(reports: list[Reports], hard_core_A: float) -> FilmAtoms:
    """The atoms of ``reports`` joined, counted and confirmed (module text)."""
    if not hard_core_A > 0 or not np.isfinite(hard_core_A):
        raise ValueError(f"hard_core_A must be a positive distance, Å, got {hard_core_A}")
    inside = [r.inside(r.positions) for r in reports]
    kept = [r.positions[i] for r, i in zip(reports, inside)]
    owner = np.concatenate([np.full(len(p), i) for i, p in enumerate(kept)]) if kept else np.zeros(0, int)
    points = np.concatenate(kept) if kept else np.zeros((0, 3))
    start = np.cumsum([0] + [len(p) for p in kept])
    parent = np.arange(len(points))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    trees = [cKDTree(p) if len(p) else None for p in kept]
    for a in range(len(kept)):
        for b in range(a + 1, len(kept)):
            if trees[a] is None or trees[b] is None or not _overlap(reports[a], reports[b], hard_core_A / 2):
                continue
            d_ab, j_ab = trees[b].query(kept[a], distance_upper_bound=hard_core_A / 2)
            _, j_ba = trees[a].query(kept[b], distance_upper_bound=hard_core_A / 2)
            for i, (d, j) in enumerate(zip(d_ab, j_ab)):
                if np.isfinite(d) and j_ba[j] == i:  # mutual nearest within half the hard core
                    ra, rb = root(start[a] + i), root(start[b] + j)
                    if ra != rb:
                        parent[rb] = ra
    roots = np.array([root(i) for i in range(len(points))], dtype=np.int64)
    labels, cluster = np.unique(roots, return_inverse=True)
    n = len(labels)
    positions = np.zeros((n, 3))
    np.add.at(positions, cluster, points)
    counts = np.bincount(cluster, minlength=n)
    positions /= np.maximum(counts, 1)[:, None]
    squares = np.zeros((n, 3))
    np.add.at(squares, cluster, (points - positions[cluster]) ** 2)
    with np.errstate(invalid="ignore", divide="ignore"):
        spread = np.where(counts[:, None] > 1, np.sqrt(squares / (counts[:, None] - 1)), np.nan)
    pairs = np.unique(np.stack([cluster, owner]), axis=1)  # each (atom, sub-area) once
    found_in = np.bincount(pairs[0], minlength=n).astype(np.int64)
    covered_by = np.sum([r.inside(positions) for r in reports], axis=0).astype(np.int64) if reports else found_in
    covered_by = np.maximum(covered_by, found_in)  # a mean may sit just outside an edge it was found inside
    confirmed, rate_real, rate_artefact = confirm(found_in, covered_by)
    trusted_in = None
    if reports and all(r.trusted is not None for r in reports):  # one report per fit and atom (joined)
        said = np.concatenate([np.asarray(r.trusted, bool)[i] for r, i in zip(reports, inside)])
        trusted_in = np.bincount(cluster, weights=said, minlength=n).astype(np.int64)
    return FilmAtoms(positions, found_in, covered_by, confirmed, rate_real, rate_artefact, spread, trusted_in)


def _overlap(a: Reports, b: Reports, margin_A: float) -> bool:
    """Whether two sub-areas' interiors, widened by ``margin_A``, overlap (else no report of one
    can join a report of the other)."""
    return bool(
        np.all(a.interior_A[0] - margin_A <= b.interior_A[1]) and np.all(b.interior_A[0] - margin_A <= a.interior_A[1])
    )


def rates_separate(rate_real: float, rate_artefact: float) -> bool:
    """Whether the real atoms' recurrence rate lies :data:`SAME_RATE` or more above the artefacts'."""
    return rate_real - rate_artefact >= SAME_RATE


def confirm(found_in: np.ndarray, covered_by: np.ndarray, iterations: int = 200) -> tuple[np.ndarray, float, float]:
    """Confirmed atoms by a two-binomial mixture of ``found_in`` out of ``covered_by`` (module
    text); returns (confirmed mask, the real atoms' recurrence rate, the artefacts')."""
    k, n = np.asarray(found_in, dtype=np.float64), np.asarray(covered_by, dtype=np.float64)
    if len(k) == 0:
        return np.zeros(0, dtype=bool), float("nan"), float("nan")
    p_real, p_art, share = 0.9, 0.2, 0.5
    for _ in range(iterations):
        log_real = np.log(share) + k * np.log(p_real) + (n - k) * np.log1p(-p_real)
        log_art = np.log1p(-share) + k * np.log(p_art) + (n - k) * np.log1p(-p_art)
        w = 1.0 / (1.0 + np.exp(np.clip(log_art - log_real, -700, 700)))  # P(real | k, n)
        share = float(np.clip(w.mean(), 1e-6, 1 - 1e-6))
        p_real = float(np.clip((w * k).sum() / max((w * n).sum(), 1e-12), 1e-6, 1 - 1e-6))
        p_art = float(np.clip(((1 - w) * k).sum() / max(((1 - w) * n).sum(), 1e-12), 1e-6, 1 - 1e-6))
        if p_art > p_real:
            p_real, p_art, share = p_art, p_real, 1.0 - share
    if not rates_separate(p_real, p_art):  # one population: the overlap tells nothing
        return np.zeros(len(k), dtype=bool), p_real, p_art
    log_real = np.log(share) + k * np.log(p_real) + (n - k) * np.log1p(-p_real)
    log_art = np.log1p(-share) + k * np.log(p_art) + (n - k) * np.log1p(-p_art)
    return log_real > log_art, p_real, p_art


@dataclass(frozen=True)
class PairAgreement:
    """Two sub-areas' fits on the atoms they share: ``n_a`` (``n_b``) the atoms ``a`` (``b``)
    reports in their common interior, ``agree_a`` (``agree_b``) the share of them the other fit
    reports too (NaN where it reports none there), ``common_A2`` the common interior's area.

    Where both state their precision, the atoms of ``a`` there that ``b`` reports too
    (``n_pairs``) judge it: ``offset_A`` (3,) the mean of ``b``'s place less ``a``'s (the two
    crops' frames apart: their registration, not any atom's), ``scatter_pm`` (3,) the RMS of the
    differences about it along x, y, z, and ``intervals_hold`` (3,) the share of the pairs whose
    difference lies within ``Z95 * sqrt(std_a^2 + std_b^2)`` (0.95 where both statements are
    exact and their errors independent; the two crops share their views' noise, so an error alike
    in both stays unseen and a share below 0.95 is the more telling); NaN without precisions."""

    a: str
    b: str
    n_a: int
    n_b: int
    agree_a: float
    agree_b: float
    common_A2: float
    n_pairs: int = 0
    offset_A: tuple = (math.nan,) * 3
    scatter_pm: tuple = (math.nan,) * 3
    intervals_hold: tuple = (math.nan,) * 3

    @property
    def both_ways(self) -> float:
        """The lesser of the two shares: what the pair agrees on both ways."""
        return float(min(self.agree_a, self.agree_b))

    def position_words(self) -> str:
        """The positions' agreement in words (empty without precisions)."""
        if not np.all(np.isfinite(self.intervals_hold)):
            return ""
        return (
            f"; the {self.n_pairs} atoms both report lie {self.scatter_pm[0]:.1f} / {self.scatter_pm[1]:.1f} / "
            f"{self.scatter_pm[2]:.1f} pm RMS apart (x / y / z, about a mean offset of "
            + " / ".join(f"{100 * v:.1f}" for v in self.offset_A)
            + " pm), within their stated 95% intervals for "
            + " / ".join(f"{v:.2f}" for v in self.intervals_hold)
        )


def pair_agreement(reports: list[Reports], hard_core_A: float, counted: list | None = None) -> list[PairAgreement]:
    """Every pair of ``reports`` whose interiors overlap, judged on the atoms both could see
    (``counted``: per report, a (N,) bool mask of the atoms whose share is read, each against all
    of the other's: the atoms a run trusts, say; default all).

    The common interior is the two interiors' intersection less half the hard core at each edge,
    so that an atom one fit reports just inside it has its counterpart inside the other's
    interior; an atom there agrees where the other fit's nearest report lies within half the hard
    core and it is that report's nearest (two reports of distinct atoms are never both that close
    to one point, :func:`join_reports`).

    >>> grid = np.stack(np.meshgrid(np.arange(0.0, 30, 3), np.arange(0.0, 12, 3), [0.0], indexing="ij"), -1)
    >>> atoms = grid.reshape(-1, 3)
    >>> left = Reports("left", atoms[atoms[:, 0] < 20], np.array([[0.0, 0.0], [20.0, 10.0]]))
    >>> extra = [[13.5, 4.5, 0.0]]  # an atom only the right fit reports, 2.1 Å from the nearest
    >>> right = Reports("right", np.r_[atoms[atoms[:, 0] > 8], extra], np.array([[8.0, 0.0], [30.0, 10.0]]))
    >>> [(p.n_a, p.n_b, round(p.agree_a, 3), round(p.agree_b, 3)) for p in pair_agreement([left, right], 2.2)]
    [(6, 7, 1.0, 0.857)]
    """
    half = hard_core_A / 2
    masks = counted if counted is not None else [np.ones(len(r.positions), bool) for r in reports]
    out = []
    for ia, a in enumerate(reports):
        for ib in range(ia + 1, len(reports)):
            b = reports[ib]
            common = common_interior(a, b, half)
            if common is None:
                continue
            lo, hi = common.interior_A
            inner = [r.inside(r.positions) for r in (a, b)]
            pa, pb = a.positions[inner[0]], b.positions[inner[1]]
            ma, mb = np.asarray(masks[ia], bool)[inner[0]], np.asarray(masks[ib], bool)[inner[1]]
            shares, matched = [], []
            for mine, theirs, mask in ((pa, pb, ma), (pb, pa, mb)):
                which = np.flatnonzero(common.inside(mine) & mask)
                if len(which) == 0 or len(theirs) == 0:
                    shares.append((len(which), math.nan))
                    matched.append((which[:0], which[:0]))
                    continue
                d, j = cKDTree(theirs).query(mine[which], distance_upper_bound=half)
                back = cKDTree(mine).query(theirs[np.minimum(j, len(theirs) - 1)])[1]
                mutual = np.isfinite(d) & (back == which)
                shares.append((len(which), float(mutual.mean())))
                matched.append((which[mutual], j[mutual]))
            (n_a, agree_a), (n_b, agree_b) = shares
            positions = _positions_agree(a, b, inner, *matched[0])
            out.append(PairAgreement(a.name, b.name, n_a, n_b, agree_a, agree_b, float(np.prod(hi - lo)), *positions))
    return out


def common_interior(a: Reports, b: Reports, margin_A: float) -> Reports | None:
    """The two reports' interiors' intersection less ``margin_A`` at each edge, as a
    :class:`Reports` of no atoms (its :meth:`~Reports.inside` the test); None where it is empty."""
    lo = np.maximum(a.interior_A[0], b.interior_A[0]) + margin_A
    hi = np.minimum(a.interior_A[1], b.interior_A[1]) - margin_A
    return None if np.any(hi <= lo) else Reports("", np.zeros((0, 3)), np.stack([lo, hi]))


def _positions_agree(a: Reports, b: Reports, inner: list, ia: np.ndarray, ib: np.ndarray) -> tuple:
    """:class:`PairAgreement`'s ``n_pairs, offset_A, scatter_pm, intervals_hold`` for the pairs
    ``ia`` (of ``a``'s interior atoms) and ``ib`` (of ``b``'s)."""
    nan = (math.nan,) * 3
    if a.position_std_A is None or b.position_std_A is None or len(ia) == 0:
        return len(ia), nan, nan, nan
    difference = b.positions[inner[1]][ib] - a.positions[inner[0]][ia]
    offset = difference.mean(axis=0)
    about = difference - offset
    allowed = Z95 * np.hypot(
        np.asarray(a.position_std_A, np.float64)[inner[0]][ia], np.asarray(b.position_std_A, np.float64)[inner[1]][ib]
    )
    with np.errstate(invalid="ignore"):
        hold = np.mean(np.abs(about) <= allowed, axis=0)
    return (
        len(ia),
        tuple(offset.tolist()),
        tuple((100 * np.sqrt(np.mean(about**2, axis=0))).tolist()),
        tuple(hold.tolist()),
    )


def write_overlaps(pairs: list[PairAgreement], path) -> None:
    """``pairs`` as a CSV table: a, b, n_a, n_b, agree_a, agree_b, common_A2, and the positions'
    agreement (:class:`PairAgreement`): n_pairs, offset_{x,y,z}_A, scatter_{x,y,z}_pm,
    hold_{x,y,z}."""
    axes = ("x", "y", "z")
    head = ["a,b,n_a,n_b,agree_a,agree_b,common_A2,n_pairs"]
    head += [f"{what}_{x}{unit}" for what, unit in (("offset", "_A"), ("scatter", "_pm"), ("hold", "")) for x in axes]
    with open(path, "w") as f:
        f.write(",".join(head) + "\n")
        f.writelines(
            f"{p.a},{p.b},{p.n_a},{p.n_b},{p.agree_a:.4f},{p.agree_b:.4f},{p.common_A2:.1f},{p.n_pairs},"
            + ",".join(f"{v:.4f}" for v in (*p.offset_A, *p.scatter_pm, *p.intervals_hold))
            + "\n"
            for p in pairs
        )
