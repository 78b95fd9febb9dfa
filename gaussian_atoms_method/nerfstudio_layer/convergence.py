"""When to stop: the atoms are settled once further steps would move them by less than the
data can tell apart.

Checked after each refine interval's densify / prune / merge: the Gaussians now are matched to
those at the last check (mutual nearest neighbours within the merge distance: closer ones would
be one atom); settled when at most ``changed_fraction`` of them were added or removed and the
RMS step of the matched positions is below ``fraction`` of the atoms' median noise-limited
precision (the Cramér-Rao bound, :mod:`gaussian_atoms_method.atoms.uncertainty`), at two checks
in a row.  Measured on Au noise 200: stops at step 2,300 with 10.4 vs 10.1 pm, the same TPR and
false positives (docs/performance.md, convergence stop).  A count that must hold exactly never
held on the 20,000- and 54,000-atom particles: a few dozen faint Gaussians still went per
interval at step 2,900.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch
from scipy.spatial import cKDTree

Precision = Callable[[float | None], "tuple[np.ndarray, float] | None"]


@dataclass
class ConvergenceCheck:
    """State of the convergence test: the positions at the last check, the settled checks in a
    row and the pixel noise (estimated from the residuals at the first check, then kept)."""

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
    settled_checks: int = 0
    noise: float | None = None

    def update(self, step: int, positions: torch.Tensor, length_scale: float, precision: Precision) -> bool:
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
        """
        if step < self.warmup_length or step % self.refine_every != 0:
            return False
        positions = positions.detach().double().cpu().clone()
        previous, self.previous = self.previous, positions
        if previous is None or len(previous) == 0 or len(positions) == 0:
            self.settled_checks = 0
            return False
        before, now = mutual_nearest(previous.numpy(), positions.numpy(), self.match_distance)
        if len(previous) + len(positions) - 2 * len(now) > self.changed_fraction * max(len(previous), len(positions)):
            self.settled_checks = 0
            return False
        step_A = float((positions[now] - previous[before]).square().sum(dim=1).mean().sqrt()) / length_scale
        result = precision(self.noise)
        if result is None:
            return False
        std, self.noise = result
        precision_A = float(np.median(np.sqrt((std**2).sum(axis=1))))
        self.settled_checks = self.settled_checks + 1 if step_A < self.fraction * precision_A else 0
        return self.settled_checks >= 2


def mutual_nearest(a: np.ndarray, b: np.ndarray, within: float = math.inf) -> tuple[np.ndarray, np.ndarray]:
    """Index arrays ``(i, j)`` of the pairs of (N, 3) ``a`` and (M, 3) ``b`` that are each
    other's nearest neighbour and closer than ``within``."""
    if len(a) == 0 or len(b) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    distance, nearest_in_b = cKDTree(b).query(a)
    _, nearest_in_a = cKDTree(a).query(b)
    i = np.nonzero((nearest_in_a[nearest_in_b] == np.arange(len(a))) & (distance < within))[0]
    return i, nearest_in_b[i]
