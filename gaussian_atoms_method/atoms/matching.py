"""Scoring predicted atoms against the truth, as in the paper.

A true atom is found when a predicted atom lies within ``radius_A`` (0.75 Å) of it, matched
one-to-one: a predicted atom can explain one true atom only.  The matching is a maximum
matching of minimal total distance, solved exactly per connected group of candidate pairs
(groups are tiny because atoms are much further apart than the radius).
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree


def match_atoms(pred_A: np.ndarray, true_A: np.ndarray, radius_A: float = 0.75) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one matching of predicted to true positions within a radius.

    Parameters
    ----------
    pred_A : (P, 3) array, Å
    true_A : (T, 3) array, Å
    radius_A : float
        Largest distance of a match (inclusive), Å.

    Returns
    -------
    pred_idx, true_idx : (M,) int arrays
        Matched pairs: ``pred_A[pred_idx[k]]`` is matched with ``true_A[true_idx[k]]``.
        Among all matchings with the most pairs, the one of least total distance.
    """
    if radius_A <= 0:
        raise ValueError(f"radius_A must be positive, got {radius_A}")
    pred_A = np.asarray(pred_A, dtype=np.float64).reshape(-1, 3)
    true_A = np.asarray(true_A, dtype=np.float64).reshape(-1, 3)
    empty = np.zeros(0, dtype=np.int64)
    if len(pred_A) == 0 or len(true_A) == 0:
        return empty, empty
    dist = cKDTree(pred_A).sparse_distance_matrix(cKDTree(true_A), radius_A, output_type="coo_matrix")
    p, t, d = dist.row, dist.col, dist.data
    # Exact zero distances are dropped by sparse storage; add them back.
    zero_p, zero_t = _coincident_pairs(pred_A, true_A)
    if len(zero_p):
        p, t, d = np.concatenate([p, zero_p]), np.concatenate([t, zero_t]), np.concatenate([d, np.zeros(len(zero_p))])
    if len(p) == 0:
        return empty, empty
    n_p = len(pred_A)
    graph = coo_matrix((np.ones(len(p)), (p, n_p + t)), shape=(n_p + len(true_A),) * 2)
    _, labels = connected_components(graph, directed=False)
    comp = labels[p]
    order = np.argsort(comp, kind="stable")
    p, t, d, comp = p[order], t[order], d[order], comp[order]
    starts = np.flatnonzero(np.r_[True, comp[1:] != comp[:-1]])
    ends = np.r_[starts[1:], len(comp)]
    alone = ends - starts == 1  # the common case, taken at once: an isolated pair
    out_p, out_t = [p[starts[alone]]], [t[starts[alone]]]
    for s, e in zip(starts[~alone], ends[~alone]):
        up, ip = np.unique(p[s:e], return_inverse=True)
        ut, it = np.unique(t[s:e], return_inverse=True)
        # Non-edges cost more than any set of edges, so the assignment maximises the number of
        # pairs first and minimises their total distance second.
        big = (e - s + 1) * (radius_A + 1.0)
        cost = np.full((len(up), len(ut)), big)
        cost[ip, it] = d[s:e]
        from scipy.optimize import linear_sum_assignment  # 40 ms to import; only where pairs compete

        rows, cols = linear_sum_assignment(cost)
        keep = cost[rows, cols] < big
        out_p.append(up[rows[keep]])
        out_t.append(ut[cols[keep]])
    return np.concatenate(out_p).astype(np.int64), np.concatenate(out_t).astype(np.int64)


def _coincident_pairs(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every pair of a point of ``a`` and one of ``b`` at exactly the same place: the points of
    ``a`` whose nearest in ``b`` is at distance zero, then all of theirs (lists only for the
    points that have one)."""
    tree = cKDTree(b)
    distance, _ = tree.query(a, workers=-1)
    hit = np.flatnonzero(distance == 0.0)
    if len(hit) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    found = tree.query_ball_point(a[hit], 0.0)
    return np.repeat(hit, [len(js) for js in found]).astype(np.int64), np.asarray(
        [j for js in found for j in js], dtype=np.int64
    )


def global_shift(
    pred_A: np.ndarray, true_A: np.ndarray, radius_A: float = 0.75, max_iterations: int = 50
) -> np.ndarray:
    """The Miao group's alignment: iterate a global mean shift of the predictions onto their matches.

    Returns the (3,) shift (Å) that, added to ``pred_A``, minimises the mean offset of matched pairs.
    """
    shift = np.zeros(3)
    for _ in range(max_iterations):
        pi, ti = match_atoms(pred_A + shift, true_A, radius_A)
        if len(pi) == 0:
            break
        step = (true_A[ti] - (pred_A[pi] + shift)).mean(axis=0)
        shift += step
        if np.linalg.norm(step) < 1e-6:
            break
    return shift


def shifted_errors(
    pred_A: np.ndarray, true_A: np.ndarray, radius_A: float = 0.75
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The predictions ``pred_A`` (N, 3) moved by :func:`global_shift` onto ``true_A`` (M, 3) and
    matched within ``radius_A``: the matched indices ``(pi, ti)`` and each pair's (K, 3) error
    (Å, prediction after the shift less truth), as the replicas' interval scores read them.

    >>> pred, true = np.array([[0.1, 0.0, 0.0], [5.3, 0.0, 0.0]]), np.array([[0.0, 0, 0], [5.0, 0, 0]])
    >>> pi, ti, error = shifted_errors(pred, true)
    >>> pi.tolist(), error[:, 0].round(2).tolist()
    ([0, 1], [-0.1, 0.1])
    """
    shift = global_shift(pred_A, true_A, radius_A)
    pi, ti = match_atoms(pred_A + shift, true_A, radius_A)
    return pi, ti, pred_A[pi] + shift - true_A[ti]


def score_atoms(
    pred_A: np.ndarray,
    true_A: np.ndarray,
    radius_A: float = 0.75,
    mean_shift: bool = False,
    pred_species=None,
    true_species=None,
    true_counted=None,
) -> dict:
    """The paper's scores for a predicted atom set.

    Parameters
    ----------
    pred_A, true_A : (P, 3), (T, 3) Å
    radius_A : float
        Matching radius, Å.
    mean_shift : bool
        Align first by the Miao group's iterated global mean shift (reported as ``shift_A``).
    pred_species, true_species : (P,), (T,) arrays of str, optional
        With both, ``species_accuracy`` is the fraction of matched pairs of equal species.
    true_counted : (T,) bool array, optional
        The true atoms the scores count, for a truth wider than the field scored (a film's whole
        model against one sub-area): every atom is matched, but a true atom outside is neither
        found nor missed, and a predicted atom on it neither found nor false (``n_true_uncounted``
        says how many were left out, where any were).

    Returns
    -------
    dict with
        ``n_true``, ``n_pred``, ``n_matched``;
        ``tpr``: fraction of true atoms matched;
        ``fp_per_true_atom``: unmatched predicted atoms per true atom;
        ``precision``: fraction of predicted atoms matched;
        ``rmsd_pm``: root-mean-square distance of matched pairs, pm (NaN if none);
        ``radius_A``: the matching radius; and ``shift_A``, ``species_accuracy`` when asked.

    >>> truth = np.array([[0.0, 0, 0], [3.0, 0, 0], [30.0, 0, 0]])
    >>> s = score_atoms(truth[:2] + 0.1, truth, true_counted=np.array([True, True, False]))
    >>> s["tpr"], s["fp_per_true_atom"], s["n_true_uncounted"]
    (1.0, 0.0, 1)
    """
    pred_A = np.asarray(pred_A, dtype=np.float64).reshape(-1, 3)
    true_A = np.asarray(true_A, dtype=np.float64).reshape(-1, 3)
    extra = {}
    counted = np.ones(len(true_A), bool) if true_counted is None else np.asarray(true_counted, bool)
    if not counted.all():
        extra["n_true_uncounted"] = int((~counted).sum())
    if mean_shift:
        shift = global_shift(pred_A, true_A[counted], radius_A)
        pred_A = pred_A + shift
        extra["shift_A"] = shift.tolist()
    pi, ti = match_atoms(pred_A, true_A, radius_A)
    scored = counted[ti]  # a pair on an uncounted true atom: neither found nor false
    pi, ti = pi[scored], ti[scored]
    if pred_species is not None and true_species is not None and len(pi):
        extra["species_accuracy"] = float(np.mean(np.asarray(pred_species)[pi] == np.asarray(true_species)[ti]))
    n_true, n_pred, n_m = int(counted.sum()), len(pred_A) - int((~scored).sum()), len(pi)
    err = pred_A[pi] - true_A[ti]
    return {
        "n_true": n_true,
        "n_pred": n_pred,
        "n_matched": n_m,
        "tpr": n_m / n_true if n_true else float("nan"),
        "fp_per_true_atom": (n_pred - n_m) / n_true if n_true else float("nan"),
        "precision": n_m / n_pred if n_pred else float("nan"),
        "rmsd_pm": float(np.sqrt((err**2).sum(axis=1).mean()) * 100.0) if n_m else float("nan"),
        "radius_A": radius_A,
        **extra,
    }


def uncount_straddling(
    true_A: np.ndarray, counted: np.ndarray, reported_A: np.ndarray, beyond_A: np.ndarray, radius_A: float = 0.75
) -> np.ndarray:
    """``counted`` (M,) bool less the true atoms ``true_A`` (M, 3) whose partner, matched one to one
    within ``radius_A`` among the reported atoms ``reported_A`` (N, 3) and the Gaussians a run
    placed beyond its field ``beyond_A`` (K, 3), lies beyond it: the mirror of a reported atom on
    a true one beyond the field (:func:`score_atoms`' ``true_counted``), neither found nor missed.
    At the field's edge along the tilt axis an atom's image is cut by the detector's edge and its
    place across the edge is known to a few tenths of an Å: on a replica of a Ta sub-area 9 of the
    15 true atoms missed lay within 1 Å inside the edge, each with the run's Gaussian just beyond it.

    >>> truth = np.array([[0.0, 9.9, 0], [0.0, 5.0, 0], [0.0, 0.0, 0]])
    >>> uncount_straddling(truth, np.ones(3, bool), truth[1:] + 0.1, np.array([[0.0, 10.2, 0]])).tolist()
    [False, True, True]
    """
    counted = np.array(counted, dtype=bool)
    beyond_A = np.asarray(beyond_A, dtype=np.float64).reshape(-1, 3)
    if len(beyond_A) == 0:
        return counted
    reported_A = np.asarray(reported_A, dtype=np.float64).reshape(-1, 3)
    pi, ti = match_atoms(np.concatenate([reported_A, beyond_A]), np.asarray(true_A, np.float64), radius_A)
    counted[ti[pi >= len(reported_A)]] = False
    return counted
