"""Whether the data can tell two nearby Gaussians from one: the merge test by likelihood.

Along a limited tilt range's missing wedge an atom's back-projection is elongated; at low dose
the fit can share one atom between two Gaussians 1-1.5 Å apart, each with part of its mass.
No distance threshold separates that pair from two real neighbours (C-C bonds are 1.42 Å), but
the data do: replacing the pair by one Gaussian changes every projection by a known image, and
when that change is lost in the noise the data cannot resolve two atoms there.

For Gaussians ``a`` of masses ``m_a``, projected positions ``p_a`` and widths ``s_a`` the
projections are ``sum_a m_a g(x - p_a; s_a)`` (``g`` the normalised 2D Gaussian: an isotropic 3D
Gaussian projects to a 2D one of the same width).  The change from the pair ``(i, j)`` to the one
Gaussian ``c`` that keeps their mass ``M = m_i + m_j``, centre of mass and second moment has
squared norm, per view, exactly

    E = sum_ab w_a w_b N(p_a - p_b; 0, s_a^2 + s_b^2),   w = (m_i, m_j, -M)

(``N`` the 2D normal density: the integral of a product of two normalised Gaussians).  Summed
over pixels of area ``A`` with noise variance ``v`` it is the chi-square the merge costs,
``sum_views E / (A v)``.  A pair whose chi-square stays below a level the noise reaches is one
atom as far as the data go.  This is the "change in likelihood when it is removed" test of
issue 15, with the pair's Gaussians removed into their merged one.

Pure numpy; lengths in any one unit (the caller's), masses in data units times length^2.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from gaussian_atoms_method.physics.arrays import unique_keys

SEARCH_WIDTHS = 3.0
"""Pairs farther apart than this many combined widths ``sqrt(s_i^2 + s_j^2)`` are not tested:
two equal Gaussians 3 combined widths (4.2 widths) apart dip to a fifth of their peak between
them in every view that sees their separation, so they never look like one atom, and the test
would only merge a negligible mass (the prune's business) into a distant atom."""


def candidate_pairs(positions: np.ndarray, sigmas: np.ndarray) -> np.ndarray:
    """(K, 2) index pairs ``i < j`` closer than :data:`SEARCH_WIDTHS` combined widths.

    Parameters
    ----------
    positions : (N, 3) array
    sigmas : (N,) array, same length unit

    The search radius of a pair of the narrower 95% is set by their widest; each of the widest
    5% is searched on its own radius (when they are more than 1.25 times wider): Gaussians
    growing in the vacuum can be twice as wide as the atoms, and one search at the widest width
    returns many times the pairs it keeps.
    """
    if len(positions) < 2:
        return np.zeros((0, 2), dtype=np.int64)
    tree = cKDTree(positions)
    cut = float(np.percentile(sigmas, 95))
    if sigmas.max() <= 1.25 * cut:  # the widest no wider than the rest: one search at its radius is cheaper
        cut = float(sigmas.max())
    wide = np.flatnonzero(sigmas > cut)
    found = [
        tree.query_pairs(SEARCH_WIDTHS * np.sqrt(2.0) * cut, output_type="ndarray").astype(np.int64).reshape(-1, 2)
    ]
    if len(wide):
        reach = SEARCH_WIDTHS * np.sqrt(sigmas[wide] ** 2 + float(sigmas.max()) ** 2)
        near = tree.query_ball_point(positions[wide], reach)
        i = np.repeat(wide, [len(n) for n in near])
        j = np.concatenate([np.asarray(n, dtype=np.int64) for n in near])
        found.append(np.stack([np.minimum(i, j), np.maximum(i, j)], axis=1)[i != j])
    pairs = found[0]
    if len(found) > 1:
        n = len(positions)
        key = unique_keys(np.concatenate([f[:, 0] * n + f[:, 1] for f in found]))  # each pair once
        pairs = np.stack([key // n, key % n], axis=1)
    d = np.linalg.norm(positions[pairs[:, 0]] - positions[pairs[:, 1]], axis=1)
    return pairs[d <= SEARCH_WIDTHS * np.hypot(sigmas[pairs[:, 0]], sigmas[pairs[:, 1]])]


def merged_moments(
    positions: np.ndarray, sigmas: np.ndarray, masses: np.ndarray, pairs: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The one isotropic Gaussian each pair would become: its centre of mass (K, 3) and the width
    (K,) that keeps the pair's second moment, ``s_c^2 = sum m (s^2 + |x - x_c|^2 / 3) / M``."""
    m = masses[pairs]  # (K, 2)
    total = m.sum(axis=1)
    w = m / total[:, None]
    centre = (w[:, :, None] * positions[pairs]).sum(axis=1)
    spread = ((positions[pairs] - centre[:, None, :]) ** 2).sum(axis=-1) / 3.0
    return centre, np.sqrt((w * (sigmas[pairs] ** 2 + spread)).sum(axis=1))


def merge_energy(
    positions: np.ndarray,
    sigmas: np.ndarray,
    masses: np.ndarray,
    pairs: np.ndarray,
    view_dirs: np.ndarray,
    chunk: int = 4096,
    merged: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """(K,) squared norm of the change in the projections, summed over the views, when each pair
    becomes its merged Gaussian (:func:`merged_moments`, or ``merged``); units mass^2 / length^2.

    Parameters
    ----------
    positions : (N, 3); sigmas, masses : (N,)
    pairs : (K, 2) int array
    view_dirs : (V, 3) beam directions (normalised here)
    merged : ((K, 3), (K,)) arrays, optional
        The merged Gaussians' centres and widths, if not :func:`merged_moments`'.

    The pairs go in chunks of ``chunk`` (their (K, V) kernels are held at once).
    """
    if len(pairs) > chunk:
        parts = [
            (k, None if merged is None else (merged[0][k : k + chunk], merged[1][k : k + chunk]))
            for k in range(0, len(pairs), chunk)
        ]
        return np.concatenate(
            [merge_energy(positions, sigmas, masses, pairs[k : k + chunk], view_dirs, chunk, part) for k, part in parts]
        )
    if len(pairs) == 0:
        return np.zeros(0)
    centre, s_c = merged_moments(positions, sigmas, masses, pairs) if merged is None else merged
    s2 = np.stack([sigmas[pairs[:, 0]] ** 2, sigmas[pairs[:, 1]] ** 2, s_c**2], axis=1)  # (K, 3)
    w = np.stack([masses[pairs[:, 0]], masses[pairs[:, 1]], -masses[pairs].sum(axis=1)], axis=1)
    u = view_dirs / np.linalg.norm(view_dirs, axis=1, keepdims=True)
    # The sum is symmetric in (a, b): each Gaussian with itself is 1 / (4 pi s_a^2) in every
    # view, and the three cross terms count twice (3 exponentials a view instead of 9).
    energy = len(u) * (w**2 / (4.0 * np.pi * s2)).sum(axis=1)
    pos = (positions[pairs[:, 0]], positions[pairs[:, 1]], centre)
    for a, b in ((0, 1), (0, 2), (1, 2)):
        diff = pos[a] - pos[b]  # (K, 3)
        d2 = (diff**2).sum(axis=1)[:, None] - (diff @ u.T) ** 2  # (K, V) projected |p_a - p_b|^2
        s = (s2[:, a] + s2[:, b])[:, None]
        energy += 2.0 * w[:, a] * w[:, b] * (np.exp(-d2 / (2.0 * s)) / (2.0 * np.pi * s)).sum(axis=1)
    return energy.clip(min=0.0)
