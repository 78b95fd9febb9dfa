"""Local maxima of a voxel volume, and the strongest of those closer than a distance: each
operation twice, on the host (numpy, scipy's k-d tree) and on a tensor's device (torch), side by
side.  The two give the same voxels in the same order (``tests/test_volume_filters.py``; on a
GPU ``tests/test_cuda.py``).  The start from a back-projection (:mod:`.candidates`), the
deconvolution's remainders, the residual searches and the baselines' tracing use them."""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.spatial import cKDTree

from gaussian_atoms_method.atoms import host_filters
from gaussian_atoms_method.atoms.volume_filters import off_cpu
from gaussian_atoms_method.atoms.voxel_pairs import pairs_within

# ---------------------------------------------------------------- on the host


def local_maxima_host(volume: np.ndarray, level: float = 0.0) -> np.ndarray:
    """(M, 3) integer indices of the voxels that are maxima of their 3x3x3 neighbourhood and
    above ``level`` (and 0), excluding the border voxels (no neighbours for the sub-voxel fit),
    in C order.  Where few voxels clear the level, only those are compared with their 26
    neighbours: at the start's levels that is a few thousandths of the voxels, and the search
    skips a full maximum filter's pass over the volume."""
    above = volume > max(level, 0.0)
    above[[0, -1], :, :] = above[:, [0, -1], :] = above[:, :, [0, -1]] = False
    if np.count_nonzero(above) > volume.size // 100:  # many: one pass of the maximum filter is cheaper
        return np.argwhere(above & (volume == host_filters.maximum_filter3(volume)))
    peaks = np.argwhere(above)
    value = volume[tuple(peaks.T)]
    keep = np.ones(len(peaks), dtype=bool)
    for offset in np.ndindex(3, 3, 3):
        if offset != (1, 1, 1):
            keep &= value >= volume[tuple((peaks + np.array(offset) - 1).T)]
    return peaks[keep]


def suppress_within_host(positions: np.ndarray, order: np.ndarray, min_distance: float) -> np.ndarray:
    """Indices kept when visiting ``positions`` in ``order`` and dropping any point within
    ``min_distance`` (inclusive) of one already kept."""
    tree = cKDTree(positions)
    neighbours = tree.query_ball_point(positions, min_distance)
    suppressed = np.zeros(len(positions), dtype=bool)
    kept = []
    for i in order:
        if suppressed[i]:
            continue
        kept.append(i)
        suppressed[neighbours[i]] = True
    return np.asarray(kept, dtype=np.int64)


def separated_maxima_host(
    data: np.ndarray, spacing_A: float, min_distance_A: float, level: float = -math.inf
) -> np.ndarray:
    """(M, 3) voxel indices of local maxima of ``data`` above ``level``, strongest first,
    ``min_distance_A`` apart."""
    peaks = local_maxima_host(data, level)
    if len(peaks) == 0:
        return np.zeros((0, 3), dtype=np.int64)
    order = np.argsort(-data[tuple(peaks.T)], kind="stable")
    return peaks[suppress_within_host(peaks * spacing_A, order, min_distance_A)]


# ---------------------------------------------------------------- on the device


def local_maxima_device(volume: torch.Tensor, level: float = 0.0, pooled: bool | None = None) -> np.ndarray:
    """(M, 3) integer indices (C order) of the voxels of a 3D tensor that are maxima of their
    3x3x3 neighbourhood (ties count) and above ``level`` and 0, excluding the border voxels:

    :func:`local_maxima_host` on the tensor's device, only the
    indices copied back.  ``pooled`` (default: off the CPU) compares every voxel with a 3x3x3
    maximum pool; on the CPU the numpy search of only the voxels above the level is faster."""
    if not off_cpu(volume, pooled):
        return local_maxima_host(volume.numpy(), level)
    neighbourhood = torch.nn.functional.max_pool3d(volume[None, None], 3, stride=1, padding=1)[0, 0]
    peak = (volume >= neighbourhood) & (volume > max(float(level), 0.0))
    peak[[0, -1], :, :] = False
    peak[:, [0, -1], :] = False
    peak[:, :, [0, -1]] = False
    return torch.nonzero(peak).cpu().numpy()


def separated_maxima_device(
    volume: torch.Tensor, spacing_A: float, min_distance_A: float, level: float = -math.inf
) -> np.ndarray:
    """:func:`separated_maxima_host` of a tensor: (M, 3) voxel
    indices of local maxima above ``level``, strongest first, ``min_distance_A`` apart.  The
    maxima are found on the tensor's device; the strongest-first suppression there too off the
    CPU (:func:`suppress_within_device`), on the CPU with the host's k-d tree."""
    found = local_maxima_device(volume, level)
    if len(found) == 0:
        return np.zeros((0, 3), dtype=np.int64)
    if off_cpu(volume, None):
        return found[
            suppress_within_device(
                torch.as_tensor(found, device=volume.device), values_at(volume, found), spacing_A, min_distance_A
            )
        ]
    order = np.argsort(-values_at(volume, found), kind="stable")
    return found[suppress_within_host(found * spacing_A, order, min_distance_A)]


def suppress_within_device(
    points: torch.Tensor, values: np.ndarray, spacing_A: float, min_distance_A: float
) -> np.ndarray:
    """:func:`suppress_within_host` of the (M, 3) integer voxel
    ``points`` (a tensor) visited strongest ``values`` first (ties in index order), on their
    device: the indices kept, in the visit's order.  The pairs within ``min_distance_A``
    (inclusive) come from :func:`.voxel_pairs.pairs_within`; the visit is solved in rounds, each
    point kept once every stronger neighbour is decided and none was kept, suppressed once one
    was kept: the greedy visit's result, in as many rounds as its longest chain of decisions,
    on the device rather than the host."""
    dev, n = points.device, len(points)
    rank = torch.empty(n, dtype=torch.long, device=dev)
    rank[torch.as_tensor(np.argsort(-np.asarray(values), kind="stable"), device=dev)] = torch.arange(n, device=dev)
    reach = int(math.floor(min_distance_A / spacing_A + 1e-9))
    stronger, weaker = [], []
    for a, b in pairs_within(points, reach):
        close = ((points[a].double() * spacing_A - points[b].double() * spacing_A) ** 2).sum(
            dim=1
        ) <= min_distance_A**2  # as the k-d tree reads it
        a, b = a[close], b[close]
        first = rank[a] < rank[b]
        stronger.append(torch.where(first, a, b))
        weaker.append(torch.where(first, b, a))
    stronger = torch.cat(stronger) if stronger else torch.zeros(0, dtype=torch.long, device=dev)
    weaker = torch.cat(weaker) if weaker else torch.zeros(0, dtype=torch.long, device=dev)
    kept = torch.zeros(n, dtype=torch.bool, device=dev)
    suppressed = torch.zeros(n, dtype=torch.bool, device=dev)
    while True:
        hit = torch.zeros(n, dtype=torch.int32, device=dev).index_add_(0, weaker, kept[stronger].int()) > 0
        open_ = torch.zeros(n, dtype=torch.int32, device=dev).index_add_(
            0, weaker, (~(kept | suppressed))[stronger].int()
        )
        now_kept = ~hit & (open_ == 0)
        if torch.equal(now_kept, kept) and torch.equal(hit, suppressed):
            break
        kept, suppressed = now_kept, hit
    order = torch.argsort(rank)
    return order[kept[order]].cpu().numpy()


def values_at(volume: torch.Tensor, indices: np.ndarray) -> np.ndarray:
    """The (M,) float64 values of ``volume`` at (M, 3) integer voxel indices, on the host."""
    index = torch.as_tensor(np.asarray(indices, dtype=np.int64).reshape(-1, 3), device=volume.device)
    return volume[index[:, 0], index[:, 1], index[:, 2]].double().cpu().numpy()
