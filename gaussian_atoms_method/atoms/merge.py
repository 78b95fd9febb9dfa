"""Cluster merge: Gaussians closer than a threshold become one atom.

The minimum-interatomic-distance prior of the paper.  All Gaussians connected by chains of
pairs closer than the threshold form one cluster (found exactly with a k-d tree and connected
components, no per-point loop), which is replaced by a single Gaussian at the mass-weighted mean position
and width.  Its amplitude is either the mean amplitude (the paper) or the one that
conserves the cluster's integrated mass (``amplitude_rule="mass"``, the default: merging two
half-atoms gives one whole atom, so the fit does not have to regrow the lost half).

The merge is applied to the parameters and the optimiser's state as a remap
(:func:`gaussian_atoms_method.density.remap.merge_remap`).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree


def cluster_labels(
    positions: np.ndarray, threshold: float, mergeable: np.ndarray | None = None
) -> tuple[np.ndarray, int]:
    """Label the connected clusters of points closer than ``threshold`` to each other.

    Parameters
    ----------
    positions : (N, 3) array
    threshold : float
        Pairs at distance ``<= threshold`` are linked (same unit as positions).
    mergeable : (N,) bool array, optional
        Only pairs of two mergeable points are linked (the others stay alone).

    Returns
    -------
    labels : (N,) int array, cluster of each point, numbered 0..n_clusters-1
    n_clusters : int
    """
    n = len(positions)
    if n == 0:
        return np.zeros(0, dtype=np.int64), 0
    pairs = cKDTree(positions).query_pairs(threshold, output_type="ndarray")
    if mergeable is not None and len(pairs):
        pairs = pairs[mergeable[pairs[:, 0]] & mergeable[pairs[:, 1]]]
    if len(pairs) == 0:
        return np.arange(n, dtype=np.int64), n
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    n_clusters, labels = connected_components(graph, directed=False)
    return labels.astype(np.int64), int(n_clusters)


def cluster_labels_on_device(
    positions: torch.Tensor, threshold: float, mergeable: torch.Tensor | None = None
) -> tuple[np.ndarray, int]:
    """:func:`cluster_labels` of an (N, 3) tensor, found on its device: the same pairs (at
    most ``threshold`` apart, in float64; candidates from cubes of side ``threshold``,
    :func:`..atoms.voxel_pairs.pairs_within`) and the same labels (every point takes the
    lowest index of its cluster, by propagation along the pairs with pointer jumping, and the
    clusters are numbered in the order of their lowest index, as scipy's
    ``connected_components`` numbers them), without the host's k-d tree; only the labels come
    back."""
    from gaussian_atoms_method.atoms.voxel_pairs import pairs_within

    n, dev = len(positions), positions.device
    if n == 0:
        return np.zeros(0, dtype=np.int64), 0
    pos = positions.detach().double()
    cells = torch.floor((pos - pos.min(dim=0).values) / threshold).long()
    firsts, seconds = [], []
    for a, b in pairs_within(cells, 1):
        close = ((pos[a] - pos[b]) ** 2).sum(dim=1) <= threshold**2
        if mergeable is not None:
            close &= mergeable[a] & mergeable[b]
        firsts.append(a[close])
        seconds.append(b[close])
    a, b = (torch.cat(firsts), torch.cat(seconds)) if firsts else (torch.zeros(0, dtype=torch.long, device=dev),) * 2
    if len(a) == 0:
        return np.arange(n, dtype=np.int64), n
    labels = torch.arange(n, device=dev)
    while True:
        low = torch.minimum(labels[a], labels[b])
        joined = labels.scatter_reduce(0, a, low, "amin").scatter_reduce(0, b, low, "amin")
        joined = joined[joined]  # pointer jumping: a label's own label
        if torch.equal(joined, labels):
            break
        labels = joined
    clusters, numbered = torch.unique(labels, return_inverse=True)
    return numbered.cpu().numpy(), len(clusters)


def scatter_mean(values: torch.Tensor, src: torch.Tensor, dst: torch.Tensor, n_out: int) -> torch.Tensor:
    """``out[j] = mean of values[src[k]] over k with dst[k] == j``; ``values`` is (N, ...)."""
    gathered = values[src]
    out = torch.zeros((n_out,) + tuple(values.shape[1:]), dtype=values.dtype, device=values.device)
    out.index_add_(0, dst, gathered)
    counts = torch.zeros(n_out, dtype=values.dtype, device=values.device)
    counts.index_add_(0, dst, torch.ones_like(dst, dtype=values.dtype))
    return out / counts.clamp_min(1).view((-1,) + (1,) * (values.dim() - 1))


def merged_values(
    means: torch.Tensor,
    sigmas: torch.Tensor,
    amplitudes: torch.Tensor,
    labels: torch.Tensor,
    n_clusters: int,
    amplitude_rule: str = "mass",
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Position, width and combined amplitude of each cluster: mass-weighted means (``"mass"``)
    or plain means (``"mean"``, the paper).

    Parameters
    ----------
    means : (N, 3); sigmas, amplitudes : (N,)
    labels : (N,) long tensor, cluster of each Gaussian
    amplitude_rule : {"mass", "mean"}
        ``"mass"``: the merged Gaussian carries the summed integrated mass of its members;
        ``"mean"``: the mean amplitude (the paper's rule).

    Returns
    -------
    means (M, 3), sigmas (M,), amplitudes (M,)
    """
    src = torch.arange(len(labels), device=labels.device)
    if amplitude_rule == "mean":
        new_means = scatter_mean(means, src, labels, n_clusters)
        new_sigmas = scatter_mean(sigmas, src, labels, n_clusters)
        new_amps = scatter_mean(amplitudes, src, labels, n_clusters)
    elif amplitude_rule == "mass":
        # Mass-weighted position and width: a faint fragment merged into an atom moves it by
        # its share of the mass, not by half the distance.
        mass = amplitudes * (2.0 * torch.pi * sigmas**2) ** 1.5
        total = torch.zeros(n_clusters, dtype=mass.dtype, device=mass.device).index_add_(0, labels, mass)
        weight = (mass / total.clamp_min(torch.finfo(mass.dtype).tiny)[labels])[:, None]
        new_means = torch.zeros(n_clusters, means.shape[1], dtype=means.dtype, device=means.device).index_add_(
            0, labels, weight * means
        )
        new_sigmas = torch.zeros(n_clusters, dtype=sigmas.dtype, device=sigmas.device).index_add_(
            0, labels, weight[:, 0] * sigmas
        )
        new_amps = total / (2.0 * torch.pi * new_sigmas**2) ** 1.5
    else:
        raise ValueError(f"amplitude_rule must be 'mass' or 'mean', got {amplitude_rule!r}")
    return new_means, new_sigmas, new_amps


def disjoint_pair_labels(n: int, pairs: np.ndarray) -> tuple[np.ndarray, int]:
    """Labels that merge a greedy set of disjoint pairs, taken in the given order (best first):
    a pair is merged only when neither member is in an earlier merged pair.

    Unlike connected components this never chains: where A-B and B-C are both links, A-B merges
    and C stays, to be judged again against the merged AB.

    Parameters
    ----------
    n : int, number of points
    pairs : (K, 2) int array, in order of preference

    Returns
    -------
    labels : (n,) int array, numbered 0..n_clusters-1
    n_clusters : int
    """
    partner = np.full(n, -1, dtype=np.int64)
    for i, j in np.asarray(pairs, dtype=np.int64).reshape(-1, 2):
        if i != j and partner[i] < 0 and partner[j] < 0:
            partner[i], partner[j] = j, i
    root = np.where((partner >= 0) & (partner < np.arange(n)), partner, np.arange(n))
    _, labels = np.unique(root, return_inverse=True)
    return labels.astype(np.int64), int(labels.max() + 1) if n else 0
