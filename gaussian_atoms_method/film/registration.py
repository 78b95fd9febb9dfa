"""Per-view registration (shifts and gains) decided by the film's overlapping sub-areas: no truth needed.

A lone tilt series cannot tell whether learning each view's shift and gain helps: the fit's own
residual always prefers more freedom, and views it did not see share its systematic errors (on
the Ta film, registration chosen by held-out views moved the atoms 0.05-0.54 Å along the beam and
lost half of one sub-area's atoms).  Overlapping sub-areas can: they see the same atoms through
other crops, each registered apart, so the better registration is the one under which their fits
place the atoms they share closer together (:class:`~.stitch.PairAgreement`'s ``scatter_pm``)
without reporting fewer of each other's atoms.  On replicas of three Ta sub-areas (independent
physics, 0.5 px and 6.8% of misregistration each) the overlap's pairs came 1.2-1.9 pm apart with
registration against 6.4-12.0 pm without, as the truth's RMSD went 2.3-3.2 against 10.4-11.6 pm.
"""

from __future__ import annotations

import numpy as np

from gaussian_atoms_method.film.stitch import PairAgreement

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


def registration_by_overlap(tried: dict[str, list[PairAgreement]]) -> dict:
    """Which of the two sub-area sets in ``tried`` (:data:`SETS`' names -> their pairs) to keep:
    ``with_registration`` where its overlapping fits place their shared atoms closer together
    (:func:`apart_pm`) and report no fewer of each other's atoms (:func:`agree_both_ways`:
    registration never lowers that agreement), else ``without_registration``; ``decided`` False
    where the overlap cannot say (no pair judged in each set).

    >>> from gaussian_atoms_method.film.stitch import PairAgreement
    >>> def pair(pm, agree=0.97):
    ...     return PairAgreement("a", "b", 100, 100, agree, agree, 500.0, 90, (0, 0, 0), (pm, pm, pm), (1, 1, 1))
    >>> registration_by_overlap({"without_registration": [pair(10.0)], "with_registration": [pair(6.0)]})["chosen"]
    'with_registration'
    >>> registration_by_overlap({"without_registration": [pair(10.0)], "with_registration": [pair(6.0, 0.9)]})["chosen"]
    'without_registration'
    >>> registration_by_overlap({"without_registration": [], "with_registration": []})["decided"]
    False
    """
    apart = {name: apart_pm(pairs) for name, pairs in tried.items()}
    agree = {name: agree_both_ways(pairs) for name, pairs in tried.items()}
    decided = all(np.isfinite(v) for v in (*apart.values(), *agree.values()))
    better = (
        decided
        and apart["with_registration"] < apart["without_registration"]
        and agree["with_registration"] >= agree["without_registration"]
    )
    return {
        "chosen": "with_registration" if better else "without_registration",
        "decided": decided,
        "median_apart_pm": {name: (v if np.isfinite(v) else None) for name, v in apart.items()},
        "median_agree_both_ways": {name: (v if np.isfinite(v) else None) for name, v in agree.items()},
        "pairs": {name: len(pairs) for name, pairs in tried.items()},
    }


def registration_words(choice: dict) -> str:
    """:func:`registration_by_overlap`'s choice in one sentence."""
    apart, agree = choice["median_apart_pm"], choice["median_agree_both_ways"]
    if not choice["decided"]:
        return (
            "per-view shifts and gains: the overlap could not decide (no overlapping sub-areas judged their "
            "positions); kept the fits without them"
        )
    kept = "with" if choice["chosen"] == "with_registration" else "without"
    return (
        f"per-view shifts and gains decided by the overlap: kept the fits {kept} them (overlapping fits place the "
        f"atoms they share {apart['with_registration']:.1f} pm apart with them, "
        f"{apart['without_registration']:.1f} pm without, RMS in 3D, and report {agree['with_registration']:.3f} and "
        f"{agree['without_registration']:.3f} of each other's atoms; medians of "
        f"{choice['pairs']['with_registration']} pairs)"
    )
