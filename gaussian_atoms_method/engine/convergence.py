"""When to stop: the atoms are settled once further steps would move them by less than the
data can tell apart.

Checked after each refine interval's densify / prune / merge: the Gaussians now are matched to
those at the last check (mutual nearest neighbours within the merge distance: closer ones would
be one atom); settled when the mass added or removed holds at most ``changed_fraction`` of the
atoms' worth (by place: a merge or split within the hard core keeps its place's mass,
:func:`places_changed`; only Gaussians of an atom's width whose existence the data would prove
count) and the RMS step of the matched positions is below ``fraction`` of the atoms' median
precision, at two checks in a row.  The precision is the isolated atom's
Cramér-Rao bound (:mod:`gaussian_atoms_method.atoms.uncertainty`) under the residual that is
there, its level and its weight at the atoms' scale, as the model's ``precision`` reads it: on
real views the white bound at the residual's level is too strict, and the run never settles.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch
from scipy.spatial import cKDTree

from gaussian_atoms_method.atoms.evidence import proof_level

Precision = Callable[[float | None], "tuple[np.ndarray, float] | tuple[np.ndarray, float, float | None] | None"]


def _on_host(values: torch.Tensor | None) -> np.ndarray | None:
    """(N,) float64 numpy copy of a per-Gaussian tensor (None stays None)."""
    return None if values is None else values.detach().double().cpu().flatten().numpy()


def _worth(atoms: float) -> str:
    """Atoms' worth in words: whole atoms from ten up, two figures below (a set that changed by
    0.3 of an atom against 0.15 tolerated read "0 (0 tolerated)" and did not settle).

    >>> _worth(0.0), _worth(0.304), _worth(2.46), _worth(37.2)
    ('0', '0.3', '2.5', '37')
    """
    return f"{atoms:.0f}" if atoms >= 10 or atoms == 0 else f"{atoms:.2g}"


@dataclass
class ConvergenceCheck:
    """State of the convergence test: the positions at the last two checks, the settled checks
    in a row and the pixel noise (estimated from the residuals at the first check, then kept).

    Besides the verdict, each check leaves what the run can act on while unsettled
    (:mod:`.stopping`): ``positions_settled``, the checks in a row at which the matched positions
    moved less than their precision whatever the set did; ``changed`` and ``tolerated``, the
    atoms' worth of Gaussians added or removed and the share allowed, and ``churning``; ``scatter_only``, whether the
    positions
    over the last three checks only scatter about fixed places (:func:`drifting`)."""

    warmup_length: int
    refine_every: int
    fraction: float = 1.0
    changed_fraction: float = 0.0
    """Gaussians added or removed since the last check, as a share of them, that still counts
    as settled (the model passes the final prune's false discovery rate: the share of noise
    Gaussians the result itself leaves to chance)."""
    match_distance: float = math.inf
    """Normalised: a Gaussian now and one at the last check are the same atom when each is the
    other's nearest and they are closer than this (the model passes the merge distance)."""
    previous: torch.Tensor | None = None
    previous_weights: torch.Tensor | None = None
    previous_beyond: np.ndarray | None = None
    settled_checks: int = 0
    noise: float | None = None
    positions_settled: int = 0
    churning: int = 0
    """Checks in a row at which more atoms' worth was added or removed than ``tolerated``."""
    changed: float = 0.0
    tolerated: float = 0.0
    scatter_only: bool = False
    older: torch.Tensor | None = None
    """The positions at the check before ``previous``, and ``link``: the (older, previous) index
    pairs matched then."""
    link: tuple[np.ndarray, np.ndarray] | None = None
    step_A: float = math.nan
    """The last check's RMS step of the matched positions, Å; ``precision_A`` their median
    precision, Å; ``drift_A`` their drift per interval with the scatter taken out, Å
    (:func:`drift_per_interval`, NaN before three checks): what :meth:`summary` reports."""
    precision_A: float = math.nan
    drift_A: float = math.nan
    amplitude_noise: float | None = None
    """The white level the residual weighs at the atoms' scale for an amplitude, read with
    ``noise`` (the precision's third value): what a Gaussian's existence is judged against."""
    previous_existence: np.ndarray | None = None
    noise_read_settled: bool = False
    """Whether ``noise`` was read at a check where the positions had settled.  The first
    check's reading (step 300) still holds the fit's misfit, which loosens the precision; when
    the positions look settled under it, the noise is read again once and then kept."""

    def checks(self, step: int) -> bool:
        """Whether ``step`` is a check (a refine step after the warm-up)."""
        return step >= self.warmup_length and step % self.refine_every == 0

    def update(
        self,
        step: int,
        positions: torch.Tensor,
        length_scale: float,
        precision: Precision,
        atoms: torch.Tensor | None = None,
        core: float = math.inf,
        existence: np.ndarray | None = None,
        beyond: torch.Tensor | None = None,
    ) -> bool:
        """True once the atoms are settled.

        Parameters
        ----------
        step : int
        positions : (N, 3) normalised positions now
        length_scale : float
            Normalised length per Å.
        precision : callable
            ``precision(noise)`` -> ((N, 3) position precision in Å, the noise it assumed), or
            None when it cannot be computed (no tilt series).
        atoms : (N,) tensor, optional
            Each Gaussian's mass in typical atoms: a Gaussian added or removed counts as that
            many atoms changed (default one each), so a fragment the prune takes counts as the
            fraction of an atom it holds.  Zero for a Gaussian the run will not
            report (beyond the field): it neither counts nor is counted in the share tolerated.
        core : float
            The material's hard core, normalised (infinite when unknown): a merge or split
            within it keeps the place's mass, so Gaussians within it of one another, now and at
            the last check, are one place (:func:`places_changed`; the match distance where it
            is unknown).
        existence : (N,) array, optional
            Each Gaussian's existence significance under white noise of unit standard deviation
            (:func:`~gaussian_atoms_method.atoms.uncertainty.existence_significance`).  With the
            precision's amplitude level, a Gaussian whose significance under that level stays
            below :func:`~gaussian_atoms_method.atoms.evidence.proof_level` of the Gaussians
            counted is worth nothing at either check: the set that must settle is the one the
            data would prove (until they prove any, every Gaussian counts).  On a real Ta
            sub-area (8) most of the set's change after step 2,000 was fragments of a quarter
            of an atom, 2-4 standard deviations under the residual, pruned one at a time.
        beyond : (N,) tensor, optional
            The worth of each Gaussian beyond the field (zero in it), which ``atoms`` counts as
            zero: carried into a place that holds a counted Gaussian (:func:`places_changed`).
        """
        if not self.checks(step):
            return False
        positions = positions.detach().double().cpu().clone()
        weights = (
            torch.ones(len(positions), dtype=torch.float64)
            if atoms is None
            else atoms.detach().double().cpu().flatten()
        )
        previous_weights, self.previous_weights = self.previous_weights, weights
        now_beyond = _on_host(beyond)
        previous_beyond, self.previous_beyond = self.previous_beyond, now_beyond
        previous_existence, self.previous_existence = self.previous_existence, existence
        older, link = self.older, self.link
        self.older, previous, self.previous, self.scatter_only = self.previous, self.previous, positions, False
        self.link = None
        if previous is None or len(previous) == 0 or len(positions) == 0:
            self.settled_checks = self.positions_settled = 0
            return False
        before, now = mutual_nearest(previous.numpy(), positions.numpy(), self.match_distance)
        self.link = (before, now)
        # the share is of the Gaussians that count (a worth of zero: beyond the reported field)
        counted = max(int((previous_weights > 0).sum()), int((weights > 0).sum()))
        self.tolerated = self.changed_fraction * counted
        step_A = float((positions[now] - previous[before]).square().sum(dim=1).mean().sqrt()) / length_scale

        # each atom's precision under ``noise`` (None: read it now), and whether the positions moved less
        def judged(
            noise,
        ):
            result = precision(noise)
            if result is None:
                return None, False
            std, self.noise, *amplitude = result
            if amplitude and amplitude[0] is not None:
                self.amplitude_noise = amplitude[0]
            precision_A = np.sqrt((std**2).sum(axis=1))
            self.precision_A = float(np.median(precision_A))
            return precision_A, step_A < self.fraction * self.precision_A

        read_here = self.noise is None  # the first reading is this check's
        self.step_A, self.drift_A = step_A, math.nan
        precision_A, moved_less = judged(self.noise)
        # settled under an early reading: read the noise again, once
        if moved_less and not (read_here or self.noise_read_settled):
            precision_A, moved_less = judged(None)
            self.noise_read_settled = True
        if precision_A is None:
            return False
        if existence is not None and previous_existence is not None and self.amplitude_noise:
            level = proof_level(counted) * self.amplitude_noise
            proven, proven_before = torch.as_tensor(existence >= level), torch.as_tensor(previous_existence >= level)
            if bool(proven.any() or proven_before.any()):  # until the data prove any, all count
                weights, previous_weights = weights * proven, previous_weights * proven_before
        self.changed = places_changed(
            previous.numpy(),
            previous_weights.numpy(),
            positions.numpy(),
            weights.numpy(),
            (before, now),
            max(self.match_distance, core) if math.isfinite(core) else self.match_distance,
            previous_beyond,
            now_beyond,
        )
        self.noise_read_settled |= moved_less
        self.positions_settled = self.positions_settled + 1 if moved_less else 0
        if older is not None and link is not None:  # atoms matched over all three checks
            older_of = np.full(len(previous), -1)
            older_of[link[1]] = link[0]
            chained = older_of[before] >= 0
            if chained.any():
                a, b, c = (
                    x.numpy() / length_scale
                    for x in (older[older_of[before[chained]]], previous[before[chained]], positions[now[chained]])
                )
                self.scatter_only = not drifting(a, b, c, precision_A[now[chained]])
                self.drift_A = drift_per_interval(a, b, c)
        set_settled = self.changed <= self.tolerated
        self.churning = 0 if set_settled else self.churning + 1
        self.settled_checks = self.settled_checks + 1 if set_settled and self.positions_settled else 0
        return self.settled_checks >= 2

    def summary(self) -> str:
        """The last check's figures in words: the positions' step and drift against their
        precision, and the set's change against the tolerated."""
        if not math.isfinite(self.step_A):
            return "no two checks of the atoms to compare yet"
        drift = f", drifting {self.drift_A:.3f} Å" if math.isfinite(self.drift_A) else ""
        return (
            f"the positions moved {self.step_A:.3f} Å RMS over the last interval{drift}, against a median precision of "
            f"{self.precision_A:.3f} Å; the set changed by {_worth(self.changed)} atoms' worth "
            f"({_worth(self.tolerated)} tolerated)"
        )

    def restart(
        self,
        positions: torch.Tensor,
        atoms: torch.Tensor | None = None,
        existence: np.ndarray | None = None,
        beyond: torch.Tensor | None = None,
    ) -> None:
        """Compare the next check with ``positions`` (the set was changed on purpose: its
        removals are not churn), from no settled checks (``atoms``, ``existence`` and ``beyond``
        as :meth:`update` takes them)."""
        self.previous, self.older, self.link = positions.detach().double().cpu().clone(), None, None
        self.previous_existence = existence
        self.previous_beyond = _on_host(beyond)
        self.previous_weights = (
            torch.ones(len(positions), dtype=torch.float64)
            if atoms is None
            else atoms.detach().double().cpu().flatten()
        )
        self.settled_checks = self.positions_settled = self.churning = 0


def drifting(
    older_A: np.ndarray, previous_A: np.ndarray, now_A: np.ndarray, precision_A: np.ndarray, z: float = 2.0
) -> bool:
    """Whether three successive (N, 3) estimates of the positions (checks' or passes' means)
    still drift, rather than scatter about fixed positions.  Scattering alone, the step over two
    intervals is as large as over one; an atom that moves by v an interval adds 3 |v|^2 to the
    first's square over the second's.  So each atom's difference of the two squared steps, in
    units of its (N,) precision squared, has mean zero when nothing drifts: drifting when their
    mean exceeds ``z`` standard errors (one-sided, 2.3% at z = 2)."""
    d = step_excess(older_A, previous_A, now_A) / np.maximum(precision_A, 1e-12) ** 2
    return bool(d.mean() > z * d.std() / math.sqrt(max(len(d), 1)))


def step_excess(older_A: np.ndarray, previous_A: np.ndarray, now_A: np.ndarray) -> np.ndarray:
    """(N,) each position's squared step over the last two intervals less its squared step over
    the last one: 3 |v|^2 on average for a drift of v an interval, zero for scatter alone."""
    return ((now_A - older_A) ** 2).sum(axis=1) - ((now_A - previous_A) ** 2).sum(axis=1)


def drift_per_interval(older_A: np.ndarray, previous_A: np.ndarray, now_A: np.ndarray) -> float:
    """RMS drift per interval of three successive (N, 3) estimates of the positions, Å, with
    their scatter taken out: a drift of v an interval makes the step over two intervals' square
    exceed the step over one's by 3 |v|^2, and scatter adds the same to both (:func:`drifting`).
    Zero when the difference's mean is not positive."""
    d = step_excess(older_A, previous_A, now_A)
    return math.sqrt(max(float(d.mean()), 0.0) / 3.0) if len(d) else math.nan


def places_changed(
    previous: np.ndarray,
    previous_worth: np.ndarray,
    now: np.ndarray,
    now_worth: np.ndarray,
    matched: tuple[np.ndarray, np.ndarray],
    within: float,
    previous_beyond: np.ndarray | None = None,
    now_beyond: np.ndarray | None = None,
) -> float:
    """The atoms' worth added or removed between two checks: (P, 3) ``previous`` and (N, 3)
    ``now`` positions with their (P,) and (N,) worths, ``matched`` the (previous, now) index
    pairs of :func:`mutual_nearest`.  A Gaussian at one check and one at the other closer than
    ``within`` share a place (connected components of that graph); each place holding a Gaussian
    left unmatched counts the change of its total worth.  A Gaussian born or pruned counts
    whole; a merge or a split within the hard core keeps its place's worth and counts only what
    the worth changed.  On a real Ta sub-area (23) at steps 2,500-2,900 the unmatched were such
    merges (two Gaussians of 0.7-0.8 atoms each, one of 1.45 between them), 4-9 atoms' worth a
    check by Gaussian against 1-2 by place.

    ``previous_beyond`` and ``now_beyond`` (P,) and (N,): the worth of Gaussians beyond the
    reported field, which the worths count as zero.  A place that holds a counted Gaussian
    counts theirs too, so a merge across the field's edge keeps its place's worth; a place of
    Gaussians beyond the field alone counts nothing.  On a real Ta sub-area (28) most of the
    change after step 2,500 was such merges: a Gaussian of 0.5-1.2 atoms just beyond the
    detector's edge and one of 0.7-0.8 inside it, joined into one of 1.2-1.5 inside.

    >>> a, b = np.array([[0.0, 0, 0], [1.9, 0, 0]]), np.array([[0.95, 0, 0]])
    >>> merged = (np.zeros(0, int), np.zeros(0, int))
    >>> places_changed(a, np.array([0.7, 0.0]), b, np.array([1.4]), merged, 1.87)  # the edge's parent uncounted
    0.7
    >>> places_changed(a, np.array([0.7, 0.0]), b, np.array([1.4]), merged, 1.87, np.array([0.0, 0.7]), np.zeros(1))
    0.0
    """
    unmatched = np.ones(len(previous) + len(now), dtype=bool)
    unmatched[matched[0]] = False
    unmatched[len(previous) + matched[1]] = False
    if not unmatched.any():
        return 0.0
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    # Only the places that hold an unmatched Gaussian count: gather them outward from those
    # Gaussians (at 54,000 the whole graph's components cost 0.17 s a check on an H200's host).
    p_at, n_at = _reached_from_unmatched(previous, now, unmatched, within)
    pairs = cKDTree(previous[p_at]).sparse_distance_matrix(cKDTree(now[n_at]), within, output_type="coo_matrix")
    n = len(p_at) + len(n_at)
    graph = coo_matrix((np.ones(pairs.nnz), (pairs.row, len(p_at) + pairs.col)), shape=(n, n))
    _, place = connected_components(graph, directed=False)
    index = np.concatenate([p_at, len(previous) + n_at])
    signed = np.concatenate([-np.asarray(previous_worth, float), np.asarray(now_worth, float)])[index]
    change = np.bincount(place, weights=signed, minlength=n)
    if previous_beyond is not None and now_beyond is not None:
        carried = np.concatenate([-np.asarray(previous_beyond, float), np.asarray(now_beyond, float)])[index]
        counted = np.bincount(place, weights=(signed != 0).astype(float), minlength=n) > 0
        change = change + np.bincount(place, weights=carried, minlength=n) * counted
    return float(np.abs(change[np.unique(place[unmatched[index]])]).sum())


def _reached_from_unmatched(
    previous: np.ndarray, now: np.ndarray, unmatched: np.ndarray, within: float
) -> tuple[np.ndarray, np.ndarray]:
    """The indices into (P, 3) ``previous`` and (N, 3) ``now`` of every Gaussian connected to an
    unmatched one (``unmatched``: (P + N,) bool, previous first) through Gaussians of the other
    check closer than ``within``, each sorted."""
    trees = (cKDTree(previous), cKDTree(now))
    points = (previous, now)
    seen = [unmatched[: len(previous)].copy(), unmatched[len(previous) :].copy()]
    frontier = [np.nonzero(seen[0])[0], np.nonzero(seen[1])[0]]
    while len(frontier[0]) or len(frontier[1]):
        nxt = []
        for side in (0, 1):  # the other check's Gaussians near this side's frontier
            src = frontier[1 - side]
            near = trees[side].query_ball_point(points[1 - side][src], within) if len(src) else []
            found = np.unique(np.concatenate([np.zeros(0, np.int64), *(np.asarray(x, np.int64) for x in near)]))
            found = found[~seen[side][found]]
            seen[side][found] = True
            nxt.append(found)
        frontier = nxt
    return np.nonzero(seen[0])[0], np.nonzero(seen[1])[0]


def mutual_nearest(a: np.ndarray, b: np.ndarray, within: float = math.inf) -> tuple[np.ndarray, np.ndarray]:
    """Index arrays ``(i, j)`` of the pairs of (N, 3) ``a`` and (M, 3) ``b`` that are each
    other's nearest neighbour and closer than ``within``."""
    if len(a) == 0 or len(b) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    distance, nearest_in_b = cKDTree(b).query(a, workers=-1)  # every core: 0.16 s a check at 54,000 atoms on one
    _, nearest_in_a = cKDTree(a).query(b, workers=-1)
    i = np.nonzero((nearest_in_a[nearest_in_b] == np.arange(len(a))) & (distance < within))[0]
    return i, nearest_in_b[i]
