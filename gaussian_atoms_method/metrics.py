"""Scoring predicted atoms against the truth, as in the paper.

A true atom is found when a predicted atom lies within ``radius_A`` (0.75 Å) of it, matched
one-to-one: a predicted atom can explain one true atom only.  The matching is a maximum
matching of minimal total distance, solved exactly per connected group of candidate pairs
(groups are tiny because atoms are much further apart than the radius).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment
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
    out_p, out_t = [], []
    for s, e in zip(starts, ends):
        if e - s == 1:  # the common case: an isolated pair
            out_p.append(p[s : s + 1])
            out_t.append(t[s : s + 1])
            continue
        up, ip = np.unique(p[s:e], return_inverse=True)
        ut, it = np.unique(t[s:e], return_inverse=True)
        # Non-edges cost more than any set of edges, so the assignment maximises the number of
        # pairs first and minimises their total distance second.
        big = (e - s + 1) * (radius_A + 1.0)
        cost = np.full((len(up), len(ut)), big)
        cost[ip, it] = d[s:e]
        rows, cols = linear_sum_assignment(cost)
        keep = cost[rows, cols] < big
        out_p.append(up[rows[keep]])
        out_t.append(ut[cols[keep]])
    return np.concatenate(out_p).astype(np.int64), np.concatenate(out_t).astype(np.int64)


def _coincident_pairs(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pairs = cKDTree(a).query_ball_tree(cKDTree(b), 0.0)
    pa = [i for i, js in enumerate(pairs) for _ in js]
    pb = [j for js in pairs for j in js]
    return np.asarray(pa, dtype=np.int64), np.asarray(pb, dtype=np.int64)


def score_atoms(pred_A: np.ndarray, true_A: np.ndarray, radius_A: float = 0.75) -> dict:
    """The paper's scores for a predicted atom set.

    Returns
    -------
    dict with
        ``n_true``, ``n_pred``, ``n_matched``;
        ``tpr``: fraction of true atoms matched;
        ``fp_per_true_atom``: unmatched predicted atoms per true atom;
        ``precision``: fraction of predicted atoms matched;
        ``rmsd_pm``: root-mean-square distance of matched pairs, pm (NaN if none);
        ``radius_A``: the matching radius.
    """
    pred_A = np.asarray(pred_A, dtype=np.float64).reshape(-1, 3)
    true_A = np.asarray(true_A, dtype=np.float64).reshape(-1, 3)
    pi, ti = match_atoms(pred_A, true_A, radius_A)
    n_true, n_pred, n_m = len(true_A), len(pred_A), len(pi)
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
    }
