"""Per-view registration (shifts and gains) decided by the film's overlapping sub-areas: no truth needed.

A lone tilt series cannot tell whether learning each view's shift and gain helps: the fit's own
residual always prefers more freedom, and views it did not see share its systematic errors (on
the Ta film, registration chosen by held-out views moved the atoms 0.05-0.54 Å along the beam and
lost half of one sub-area's atoms).  Overlapping sub-areas can: they see the same atoms through
other crops, each registered apart, so the better registration is the one under which their fits
place the atoms they share closer together (:class:`~.stitch.PairAgreement`'s ``scatter_pm``)
without reporting fewer of each other's atoms beyond counting: decided sub-area by sub-area,
against each one's neighbours (:func:`registration_by_overlap`).  On replicas of three Ta sub-areas (independent
physics, 0.5 px and 6.8% of misregistration each) the overlap's pairs came 1.2-1.9 pm apart with
registration against 6.4-12.0 pm without, as the truth's RMSD went 2.3-3.2 against 10.4-11.6 pm.
"""

from __future__ import annotations

import numpy as np

from gaussian_atoms_method.film.stitch import PairAgreement, Reports, pair_agreement

SETS = {
    "without_registration": {"refine_alignment": False, "refine_gain": False},
    "with_registration": {"refine_alignment": True, "refine_gain": True},
}
"""The two fits of every sub-area, by their run directories' names, and the fit's options each
sets: per-view shifts and gains off, on (decided together: on the Ta film's sub-areas and their
replicas the gains brought the pairs closer again than the shifts alone)."""


def apart_pm(pairs: list[PairAgreement]) -> float:
    """The median over the ``pairs`` that state positions of the atoms' RMS distance apart in 3D
    (``sqrt(sum of scatter_pm^2)``, pm); NaN where none does (no overlap, or no precisions)."""
    stated = [
        np.sqrt(np.sum(np.square(p.scatter_pm))) for p in pairs if p.n_pairs and np.all(np.isfinite(p.scatter_pm))
    ]
    return float(np.median(stated)) if stated else float("nan")


def agree_both_ways(pairs: list[PairAgreement]) -> float:
    """The median over ``pairs`` of the share of atoms both fits report, the lesser way
    (:attr:`~.stitch.PairAgreement.both_ways`); NaN without a judged pair."""
    judged = [p.both_ways for p in pairs if np.isfinite(p.both_ways)]
    return float(np.median(judged)) if judged else float("nan")


Z_FEWER = 1.645
"""One-sided 95% normal quantile: a registration reports fewer of its neighbours' atoms only
where the atoms one fit of a pair reports and the other does not rise by more than this many
standard deviations of their count (:func:`reports_fewer`)."""


def unshared(pairs: list[PairAgreement]) -> float:
    """The atoms of ``pairs``' common interiors that one fit reports and the other does not, both
    ways, summed over the pairs (``(1 - agree_a) n_a + (1 - agree_b) n_b``; a pair with no atoms
    on one side counts none)."""
    return float(
        sum(
            (1 - p.agree_a) * p.n_a + (1 - p.agree_b) * p.n_b
            for p in pairs
            if np.isfinite(p.agree_a) and np.isfinite(p.agree_b)
        )
    )


def reports_fewer(registered: list[PairAgreement], plain: list[PairAgreement]) -> bool:
    """Whether ``registered``'s pairs share fewer atoms than ``plain``'s beyond counting: the
    unshared atoms (:func:`unshared`), each a rare event of a fit, are Poisson counts, so their
    difference varies by the sum of the two; more than :data:`Z_FEWER` of its standard
    deviations is fewer.  A single atom more is not (on replicas of Ta sub-areas 22-24, one
    atom of 700 kept sub-area 24 off a registration that brought its pairs 11.4 -> 3.7 pm
    together and its RMSD against the truth 11.4 -> 3.9 pm).

    >>> p = PairAgreement("a", "b", 700, 700, 1.0, 1.0, 400.0)
    >>> q = PairAgreement("a", "b", 700, 700, 699 / 700, 1.0, 400.0)
    >>> reports_fewer([q], [p]), reports_fewer([p], [q])
    (False, False)
    >>> reports_fewer([PairAgreement("a", "b", 700, 700, 0.99, 0.99, 400.0)], [p])
    True
    """
    more, less = unshared(registered), unshared(plain)
    return bool(more - less > Z_FEWER * np.sqrt(more + less))


def registration_by_overlap(reports: dict[str, list[Reports]], hard_core_A: float, sweeps: int = 10) -> dict:
    """Each sub-area's registration, chosen by its overlapping neighbours: ``reports`` (the two
    :data:`SETS`' names -> each sub-area's :class:`~.stitch.Reports`, in one order).

    Sub-area by sub-area, in turn until none changes (at most ``sweeps`` passes), a sub-area takes
    its fit ``with_registration`` where, against its neighbours as they stand, the atoms they share
    lie closer together (:func:`apart_pm`) and no fewer are reported by both beyond counting
    (:func:`reports_fewer`), else ``without_registration``; once from none registered and once
    from all, the mix kept whose pairs sit closest.  Registration
    can fail one sub-area and help the next (on the Ta film's second strip it brought 18-24 to
    their neighbours and put 25 ~50 pm off all of its own), so the choice is each sub-area's.
    The mix is kept only where the film's overlapping pairs, taken whole, agree no less beyond
    counting and sit closer than with no registration (else none is registered); ``decided``
    False where no sub-areas overlap."""
    base, other = SETS
    n = len(reports[base])
    table = {}
    for i in range(n):
        for j in range(i + 1, n):
            for si in SETS:
                for sj in SETS:
                    found = pair_agreement([reports[si][i], reports[sj][j]], hard_core_A)
                    if found:
                        table[i, j, si, sj] = found[0]
    overlapping = sorted({(i, j) for i, j, _, _ in table})

    def pairs_of(choice: list[str], only: int | None = None) -> list[PairAgreement]:
        return [table[i, j, choice[i], choice[j]] for i, j in overlapping if only is None or only in (i, j)]

    def better(registered: list[PairAgreement], plain: list[PairAgreement]) -> bool:
        apart, agree = (apart_pm(registered), apart_pm(plain)), (agree_both_ways(registered), agree_both_ways(plain))
        return bool(np.all(np.isfinite(apart + agree)) and apart[0] < apart[1] and not reports_fewer(registered, plain))

    def settled(choice: list[str]) -> list[str]:
        for _ in range(sweeps if overlapping else 0):
            before = list(choice)
            for i in range(n):
                on, off = list(choice), list(choice)
                on[i], off[i] = other, base
                choice[i] = other if better(pairs_of(on, i), pairs_of(off, i)) else base
            if choice == before:
                break
        return choice

    plain, everywhere = pairs_of([base] * n), pairs_of([other] * n)
    # from none registered and from all: one sub-area registered alone among misregistered
    # neighbours cannot show that it helps, nor one left alone among registered ones
    candidates = [c for c in (settled([base] * n), settled([other] * n)) if better(pairs_of(c), plain)]
    choice = min(candidates, key=lambda c: apart_pm(pairs_of(c))) if candidates else [base] * n
    kept = pairs_of(choice)
    names = [r.name for r in reports[base]]
    return {
        "chosen": dict(zip(names, choice)),
        "decided": bool(overlapping),
        "registered": [name for name, c in zip(names, choice) if c == other],
        "median_apart_pm": {
            key: (v if np.isfinite(v) else None)
            for key, v in (("none", apart_pm(plain)), ("all", apart_pm(everywhere)), ("chosen", apart_pm(kept)))
        },
        "median_agree_both_ways": {
            key: (v if np.isfinite(v) else None)
            for key, v in (
                ("none", agree_both_ways(plain)),
                ("all", agree_both_ways(everywhere)),
                ("chosen", agree_both_ways(kept)),
            )
        },
        "pairs": len(overlapping),
    }


def registration_words(choice: dict) -> str:
    """:func:`registration_by_overlap`'s choice in one sentence."""
    if not choice["decided"]:
        return (
            "per-view shifts and gains: the overlap could not decide (no sub-areas overlap); kept the fits without them"
        )
    apart, agree = choice["median_apart_pm"], choice["median_agree_both_ways"]
    registered = choice["registered"]
    which = ", ".join(registered) if registered else "none"
    return (
        f"per-view shifts and gains decided by the overlap, sub-area by sub-area: kept for {len(registered)} of "
        f"{len(choice['chosen'])} ({which}); overlapping fits place the atoms they share {apart['chosen']:.1f} pm "
        f"apart (none registered {apart['none']:.1f}, all {apart['all']:.1f}; RMS in 3D) and report "
        f"{agree['chosen']:.3f} of each other's atoms ({agree['none']:.3f}, {agree['all']:.3f}); medians of "
        f"{choice['pairs']} pairs"
    )
