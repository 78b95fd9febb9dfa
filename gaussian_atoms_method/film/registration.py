"""Per-view shifts decided by the film's overlapping sub-areas: no truth needed.

A lone tilt series cannot tell whether learning each view's shift helps: the fit's own residual
always prefers more freedom, and views it did not see share its systematic errors (on the Ta
film, registration chosen by held-out views moved the atoms 0.05-0.54 Å along the beam and lost
half of one sub-area's atoms).  Overlapping sub-areas can: they see the same atoms through other
crops, each registered apart, so the better registration is the one under which their fits place
the atoms they share closer together (:class:`~.stitch.PairAgreement`'s ``scatter_pm``).
"""

from __future__ import annotations

import numpy as np

from gaussian_atoms_method.film.stitch import PairAgreement

SETS = {"without_shifts": False, "with_shifts": True}
"""The two fits of every sub-area, by their run directories' names: ``refine_alignment`` off, on."""


def apart_pm(pairs: list[PairAgreement]) -> float:
    """The median over the ``pairs`` that state positions of the atoms' RMS distance apart in 3D
    (``sqrt(sum of scatter_pm^2)``, pm); NaN where none does (no overlap, or no precisions)."""
    stated = [
        np.sqrt(np.sum(np.square(p.scatter_pm))) for p in pairs if p.n_pairs and np.all(np.isfinite(p.scatter_pm))
    ]
    return float(np.median(stated)) if stated else float("nan")


def registration_by_overlap(tried: dict[str, list[PairAgreement]]) -> dict:
    """Which of the sub-area sets in ``tried`` (:data:`SETS`' names -> their pairs) to keep: the
    one whose overlapping fits place their shared atoms closest (:func:`apart_pm`), or
    ``without_shifts`` where the overlap cannot say (``decided`` False: no pair judged in each).

    >>> from gaussian_atoms_method.film.stitch import PairAgreement
    >>> def pair(pm):
    ...     return PairAgreement("a", "b", 100, 100, 0.97, 0.97, 500.0, 90, (0, 0, 0), (pm, pm, pm), (1, 1, 1))
    >>> registration_by_overlap({"without_shifts": [pair(10.0)], "with_shifts": [pair(6.0)]})["chosen"]
    'with_shifts'
    >>> registration_by_overlap({"without_shifts": [], "with_shifts": []})["decided"]
    False
    """
    apart = {name: apart_pm(pairs) for name, pairs in tried.items()}
    decided = all(np.isfinite(v) for v in apart.values())
    chosen = min(apart, key=apart.get) if decided else "without_shifts"
    return {
        "chosen": chosen,
        "decided": decided,
        "median_apart_pm": {name: (v if np.isfinite(v) else None) for name, v in apart.items()},
        "pairs": {name: len(pairs) for name, pairs in tried.items()},
    }


def registration_words(choice: dict) -> str:
    """:func:`registration_by_overlap`'s choice in one sentence."""
    apart = choice["median_apart_pm"]
    if not choice["decided"]:
        return (
            "per-view shifts: the overlap could not decide (no overlapping sub-areas judged their positions); "
            "kept the fits without them"
        )
    return (
        f"per-view shifts decided by the overlap: kept the fits {choice['chosen'].replace('_', ' ')} (overlapping "
        f"fits place the atoms they share {apart['with_shifts']:.1f} pm apart with them, "
        f"{apart['without_shifts']:.1f} pm without; the median of {choice['pairs']['with_shifts']} pairs, RMS in 3D)"
    )
