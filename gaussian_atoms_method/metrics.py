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


def global_shift(pred_A: np.ndarray, true_A: np.ndarray, radius_A: float = 0.75, max_iterations: int = 50) -> np.ndarray:
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


def score_atoms(
    pred_A: np.ndarray, true_A: np.ndarray, radius_A: float = 0.75, mean_shift: bool = False, pred_species=None, true_species=None
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

    Returns
    -------
    dict with
        ``n_true``, ``n_pred``, ``n_matched``;
        ``tpr``: fraction of true atoms matched;
        ``fp_per_true_atom``: unmatched predicted atoms per true atom;
        ``precision``: fraction of predicted atoms matched;
        ``rmsd_pm``: root-mean-square distance of matched pairs, pm (NaN if none);
        ``radius_A``: the matching radius; and ``shift_A``, ``species_accuracy`` when asked.
    """
    pred_A = np.asarray(pred_A, dtype=np.float64).reshape(-1, 3)
    true_A = np.asarray(true_A, dtype=np.float64).reshape(-1, 3)
    extra = {}
    if mean_shift:
        shift = global_shift(pred_A, true_A, radius_A)
        pred_A = pred_A + shift
        extra["shift_A"] = shift.tolist()
    pi, ti = match_atoms(pred_A, true_A, radius_A)
    if pred_species is not None and true_species is not None and len(pi):
        extra["species_accuracy"] = float(np.mean(np.asarray(pred_species)[pi] == np.asarray(true_species)[ti]))
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
        **extra,
    }


def voxelise_gaussians(
    positions_A: np.ndarray, sigmas_A: np.ndarray, amplitudes: np.ndarray, voxel_size_A: float, shape: tuple[int, int, int], origin_index=None, radius_sigmas: float = 4.0
) -> np.ndarray:
    """Sample a sum of isotropic Gaussians on a voxel grid.

    Parameters
    ----------
    positions_A : (M, 3) Å about the grid's origin
    sigmas_A : (M,) Å; amplitudes : (M,) 3D peak values
    voxel_size_A : float
    shape : (X, Y, Z)
    origin_index : (3,) fractional voxel index of position 0; default the middle ``(n - 1) / 2``
    radius_sigmas : float
        Each Gaussian is evaluated within this many sigmas of its centre (4: 3e-4 of its peak).

    Returns
    -------
    (X, Y, Z) float64 array: the Gaussians evaluated at the voxel centres.
    """
    import torch

    shape = tuple(int(s) for s in shape)
    origin = (np.array(shape, dtype=np.float64) - 1) / 2 if origin_index is None else np.asarray(origin_index, dtype=np.float64)
    centres = np.asarray(positions_A, dtype=np.float64) / voxel_size_A + origin  # fractional indices
    sig = np.asarray(sigmas_A, dtype=np.float64) / voxel_size_A
    amp = np.asarray(amplitudes, dtype=np.float64)
    out = torch.zeros(int(np.prod(shape)), dtype=torch.float64)
    strides = torch.tensor([shape[1] * shape[2], shape[2], 1])
    # Widths can differ by orders of magnitude (a stray wide Gaussian): visit atoms from narrow
    # to wide, each chunk with the window of its widest member, sized to ~2e7 voxel values.
    order = np.argsort(sig)
    start = 0
    while start < len(order):
        half = min(int(np.ceil(radius_sigmas * sig[order[start]])), max(shape))
        m = max(1, int(2e7 // (2 * half + 1) ** 3))
        chunk = order[start : start + m]
        half = min(int(np.ceil(radius_sigmas * sig[chunk].max())), max(shape))
        chunk = chunk[: max(1, int(2e7 // (2 * half + 1) ** 3))]
        start += len(chunk)
        offsets = torch.arange(-half, half + 1)
        c = torch.from_numpy(centres[chunk])
        s = torch.from_numpy(sig[chunk])[:, None]
        base = torch.round(c).long()
        idx = base[:, :, None] + offsets  # (m, 3, w)
        g = torch.exp(-((idx - c[:, :, None]) ** 2) / (2 * s[:, :, None] ** 2))  # separable factors
        valid = [(idx[:, a] >= 0) & (idx[:, a] < shape[a]) for a in range(3)]
        g = [torch.where(valid[a], g[:, a], 0.0) for a in range(3)]
        vals = torch.from_numpy(amp[chunk])[:, None, None, None] * g[0][:, :, None, None] * g[1][:, None, :, None] * g[2][:, None, None, :]
        flat = (
            idx[:, 0].clamp(0, shape[0] - 1)[:, :, None, None] * strides[0]
            + idx[:, 1].clamp(0, shape[1] - 1)[:, None, :, None] * strides[1]
            + idx[:, 2].clamp(0, shape[2] - 1)[:, None, None, :] * strides[2]
        )
        out.index_add_(0, flat.reshape(-1), vals.reshape(-1))
    return out.reshape(shape).numpy()


def volume_ssim(volume: np.ndarray, reference: np.ndarray) -> dict:
    """SSIM of a volume against a reference on the same grid (scikit-image).

    The data range is the reference's (max - min); both are reported with the value because
    SSIM swings with them (a mostly-vacuum box scores high for any method).
    """
    from skimage.metrics import structural_similarity

    if volume.shape != reference.shape:
        raise ValueError(f"volume shape {volume.shape} differs from the reference's {reference.shape}")
    data_range = float(reference.max() - reference.min())
    value = structural_similarity(np.asarray(volume, np.float64), np.asarray(reference, np.float64), data_range=data_range)
    return {"ssim": float(value), "ssim_data_range": data_range, "ssim_reference": "true potential blurred like the data"}
