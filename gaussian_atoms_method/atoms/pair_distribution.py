"""The material's shortest interatomic distance, read from the atoms themselves.

Every material has a shortest distance its atoms keep (C-C 1.42 Å, Si-Si 2.35 Å, Ta-Ta about
2.6 Å): its pair distribution is zero below the onset of the first peak.  A fit that explains
what its forward model cannot (a probe's tails, misalignment, a film beyond the field of view)
with extra Gaussians puts them closer to the atoms than that.  So the distance is read from the
confident atoms' pair distribution, whose main peak is the first coordination shell: its
low-side half maximum is the shortest distance.  How rare a pair at a shorter distance ``d`` is
(the prior odds of :meth:`~gaussian_atoms_method.density.strategy.DensityControl.merge_by_likelihood`)
follows the shell's low side down to ``d`` (:meth:`FirstShell.share_closer`): a pair half a
bond apart is far rarer than one just under the onset, where the position errors of a sharp
shell put many true pairs: one prior for every pair under the onset would ask nothing of a
fragment near its atom.  Checked on true structures, and with atoms split into halves, in
tests/test_pair_distribution.py.  Pure numpy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree
from scipy.special import ndtr

MIN_ATOMS = 20
"""Fewer confident atoms than this: too few to read a distribution (no distance is read)."""


def nearest_neighbour_distances(positions: np.ndarray) -> np.ndarray:
    """(N,) each position's distance to its nearest other one (N >= 2)."""
    distance, _ = cKDTree(positions).query(positions, k=2, workers=-1)
    return distance[:, 1]


HALF_MAXIMUM_Z = math.sqrt(2.0 * math.log(2.0))
"""A Gaussian falls to half its peak this many standard deviations from its centre."""
INNER_WIDTHS = 3.0
"""A Gaussian shell holds 0.1% of its pairs more than this many widths below its peak: where
most atoms have their nearest neighbour there, another shell lies below the main peak."""


@dataclass(frozen=True)
class FirstShell:
    """The first coordination shell read from N positions (:func:`first_shell`).

    Attributes
    ----------
    onset : float
        The shell's low-side half maximum, the shortest distance (same unit as the positions).
    peak : float
        The shell's maximum.
    share : float
        Share of the positions whose nearest neighbour is closer than ``onset``, at least 1 / N.
    inner_share : float
        Share whose nearest neighbour lies more than :data:`INNER_WIDTHS` widths below the peak.
    n : int
        N.
    """

    onset: float
    peak: float
    share: float
    inner_share: float
    n: int

    @property
    def width(self) -> float:
        """The low side's standard deviation, ``(peak - onset) / 1.177``."""
        return max(self.peak - self.onset, 1e-12) / HALF_MAXIMUM_Z

    def share_closer(self, distance: np.ndarray) -> np.ndarray:
        """(K,) the share of atoms with a neighbour closer than each (K,) ``distance``: below the
        onset, the shell's low side followed as a Gaussian from the ``share`` measured there,
        never below one in N (one close pair cannot be ruled out by N atoms); at and above it,
        ``share``.

        A real first shell falls faster than a Gaussian below its onset (atoms repel), so this
        overstates how common a close pair is: the prior odds it gives are the least the data
        allow.  Where most atoms have their nearest neighbour far below the peak
        (:data:`INNER_WIDTHS`), the main peak is not the first shell (the harness's carbon at
        scale 0.5 peaks at its 2.4 Å second neighbours): ``share`` at every distance."""
        distance = np.asarray(distance, dtype=np.float64)
        if self.inner_share >= 0.5:
            return np.full(distance.shape, self.share)
        tail = ndtr((distance - self.peak) / self.width) / ndtr(-HALF_MAXIMUM_Z)
        return np.where(distance < self.onset, np.clip(self.share * tail, 1.0 / self.n, self.share), self.share)


GRID_POINTS = 512
"""Points of the grid (0 to the longest pair distance) on which the pair distribution is read."""
BINS_PER_GRID_STEP = 16
"""The distances are binned this finely before the kernel sum (:func:`weighted_kernel_density`)."""


KERNEL_WIDTHS = 10.0
""":func:`weighted_kernel_density` sums each kernel this many bandwidths out: beyond, a kernel is
below exp(-50), 2e-22 of its peak, under float64's rounding of the sum."""


def weighted_kernel_density(values: np.ndarray, weights: np.ndarray, grid: np.ndarray, bandwidth: float) -> np.ndarray:
    """(G,) the Gaussian kernel density ``sum_i w_i exp(-(g - v_i)^2 / 2 h^2)`` of (K,) ``values``
    with (K,) ``weights`` on the evenly spaced (G,) ``grid``, the values first binned at
    1 / :data:`BINS_PER_GRID_STEP` of the grid's step.

    Binning moves each value by at most half a bin (1/32 of a grid step), far below the grid's
    own resolution of the onset.  Each grid point then sits on a bin, so the sum is a
    correlation of the bins' masses with one sampled kernel, read at the grid's bins and cut
    :data:`KERNEL_WIDTHS` bandwidths out: the cost is the grid times the kernel's bins, not the
    grid times the bins or the pairs (the direct sum: :func:`kernel_density_reference`)."""
    values, weights, grid = (np.asarray(a, dtype=np.float64) for a in (values, weights, grid))
    step = (grid[-1] - grid[0]) / max(len(grid) - 1, 1) / BINS_PER_GRID_STEP
    if not step > 0:
        return kernel_density_reference(values, weights, grid, bandwidth)
    index = np.clip(np.rint((values - grid[0]) / step).astype(np.int64), 0, None)
    mass = np.bincount(index, weights=weights)
    reach = int(math.ceil(KERNEL_WIDTHS * bandwidth / step))
    if 2 * reach + 1 >= len(mass):  # a kernel as wide as the bins: the sum over the occupied ones
        occupied = np.nonzero(mass)[0]
        return kernel_density_reference(grid[0] + occupied * step, mass[occupied], grid, bandwidth)
    # density[j] = sum_m padded[16 j + m] kernel[m]: with m = 16 a + b, rows of 16 bins times
    # the kernel's rows, then summed along the diagonals
    rows = -(-(2 * reach + 1) // BINS_PER_GRID_STEP)
    kernel = np.zeros(rows * BINS_PER_GRID_STEP)
    kernel[: 2 * reach + 1] = np.exp(-0.5 * (np.arange(-reach, reach + 1) * (step / bandwidth)) ** 2)
    padded = np.zeros((len(grid) - 1 + rows) * BINS_PER_GRID_STEP)
    padded[reach : reach + len(mass)] = mass[: len(padded) - reach]
    products = padded.reshape(-1, BINS_PER_GRID_STEP) @ kernel.reshape(rows, BINS_PER_GRID_STEP).T
    density = np.zeros(len(grid))
    for a in range(rows):
        density += products[a : a + len(grid), a]
    return density


def kernel_density_reference(values: np.ndarray, weights: np.ndarray, grid: np.ndarray, bandwidth: float) -> np.ndarray:
    """The direct sum of :func:`weighted_kernel_density`, in chunks of 4,096 values (bounded memory)."""
    density = np.zeros(len(grid))
    for chunk in np.array_split(np.arange(len(values)), max(1, len(values) // 4096)):
        density += (np.exp(-0.5 * ((grid[:, None] - values[None, chunk]) / bandwidth) ** 2) * weights[None, chunk]).sum(
            axis=1
        )
    return density


def shortest_distance(positions: np.ndarray) -> tuple[float, float]:
    """The shortest interatomic distance of (N, 3) ``positions`` and the share of them closer
    (:func:`first_shell`'s onset and share)."""
    shell = first_shell(positions)
    return shell.onset, shell.share


def first_shell(positions: np.ndarray) -> FirstShell:
    """The first coordination shell of (N, 3) ``positions``: its onset, the shortest distance.

    The pair distribution ``g(r)`` (pair distances within twice the median nearest-neighbour
    distance, each weighted by ``1 / r^2``: a Gaussian kernel density of Silverman's bandwidth)
    has its main peak at the first coordination shell, where every atom has several neighbours;
    an atom split in two adds one short pair, so even when every atom is split the shell still
    dominates (the nearest-neighbour distances alone would then peak at the split).  Walking down
    from the peak towards shorter distances, the first point below half the peak is the distance.

    Returns
    -------
    FirstShell
        Infinite onset and peak, share 1, with fewer than :data:`MIN_ATOMS` positions.
    """
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    n = len(positions)
    none = FirstShell(math.inf, math.inf, 1.0, 0.0, n)
    if n < MIN_ATOMS:
        return none
    nearest = nearest_neighbour_distances(positions)
    pairs = cKDTree(positions).query_pairs(2.0 * float(np.median(nearest)), output_type="ndarray")
    d = np.linalg.norm(positions[pairs[:, 0]] - positions[pairs[:, 1]], axis=1)
    d = d[d > 0]
    if len(d) < MIN_ATOMS:
        return none
    q25, q75 = np.percentile(d, [25, 75])
    bandwidth = 0.9 * max(min(float(d.std()), (q75 - q25) / 1.349), 1e-6 * float(np.median(d))) * len(d) ** (-0.2)
    grid = np.linspace(0.0, float(d.max()), GRID_POINTS)
    density = weighted_kernel_density(d, 1.0 / d**2, grid, bandwidth)
    peak = int(np.argmax(density))
    below = np.nonzero(density[: peak + 1] < 0.5 * density[peak])[0]
    shell = FirstShell(float(grid[below[-1]]) if len(below) else 0.0, float(grid[peak]), 1.0, 0.0, n)
    return replace(
        shell,
        share=max(float(np.mean(nearest < shell.onset)), 1.0 / n),
        inner_share=float(np.mean(nearest < shell.peak - INNER_WIDTHS * shell.width)),
    )
