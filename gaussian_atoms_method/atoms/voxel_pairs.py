"""Pairs of voxels within a distance of each other, found in torch on the points' device.

A k-d tree on the host lists such pairs for CLEAN (:mod:`.point_response`) and for the
strongest-first suppression of maxima (:mod:`.volume_filters`); where the volume lives on a GPU
the points are binned there instead: in cubes of the reach plus one voxel, so that two points
within reach lie in the same or neighbouring cubes, each point's candidates are the points of
the 27 cubes about its own (sorted by cube, found by binary search), taken in chunks of a
bounded number of candidates.
"""

from __future__ import annotations

import numpy as np
import torch


def pairs_within(points: torch.Tensor, reach: int, max_candidates: int = 1 << 26):
    """Every pair of the (M, 3) integer voxel ``points`` (a tensor) at most ``reach`` voxels apart
    along every axis (Chebyshev distance), as (P,) index tensors ``earlier < later`` on the
    points' device, in chunks: yields one (earlier, later) pair of tensors per chunk of at
    most ``max_candidates`` candidate pairs (at least one point's)."""
    n, dev = len(points), points.device
    if n == 0:
        return
    cube = (points - points.min(dim=0).values) // (reach + 1) + 1  # a margin of one cube on every side
    sizes = cube.max(dim=0).values + 2
    stride = torch.stack([sizes[1] * sizes[2], sizes[2], torch.ones_like(sizes[2])])
    key = (cube * stride).sum(dim=1)
    order = torch.argsort(key)
    sorted_key = key[order]
    moves = torch.as_tensor(np.array(list(np.ndindex(3, 3, 3))) - 1, device=dev)
    neighbours = key[:, None] + (moves * stride).sum(dim=1)[None, :]  # (M, 27) cube keys
    lo = torch.searchsorted(sorted_key, neighbours)
    counts = torch.searchsorted(sorted_key, neighbours, right=True) - lo
    per_point = counts.sum(dim=1)
    bounds = torch.cumsum(per_point, 0).tolist()
    lo, counts = lo.reshape(-1), counts.reshape(-1)
    start = 0
    while start < n:
        # candidates of the points before ``start``, read from the host's list
        before = bounds[start - 1] if start else 0
        stop = max(int(np.searchsorted(bounds, before + max_candidates, side="right")), start + 1)
        c = counts[27 * start : 27 * stop]
        slot = torch.repeat_interleave(torch.arange(len(c), device=dev), c, output_size=bounds[stop - 1] - before)
        offset = torch.arange(bounds[stop - 1] - before, device=dev) - (torch.cumsum(c, 0) - c)[slot]
        other = order[lo[27 * start : 27 * stop][slot] + offset]  # a point of a neighbouring cube
        this = start + slot // 27
        keep = (other < this) & ((points[this] - points[other]).abs().max(dim=1).values <= reach)
        yield other[keep], this[keep]
        start = stop
