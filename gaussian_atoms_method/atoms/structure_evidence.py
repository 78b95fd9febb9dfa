"""Evidence a practitioner checks without a truth: the reported atoms' pair distribution, their
number density and the share of them closer than the material's hard core.

A physical structure has no pair inside its hard core (:mod:`.hard_core`), a first coordination
shell at its bond length and a number density of its kind (crystalline Ta 0.0554 Å⁻³, Au 0.0590,
a-Si 0.050): a reconstruction whose atoms break either explains something else with them.
Pure numpy and scipy.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import ConvexHull, QhullError, cKDTree

R_MAX_A = 8.0
"""The pair distribution is read out to this distance (the first three shells of a metal)."""
BIN_A = 0.05
"""Its bins, Å: finer than any shell's width (0.1-0.3 Å) and than the hard core's precision."""


def pair_distribution_function(
    positions_A: np.ndarray, r_max_A: float = R_MAX_A, bin_A: float = BIN_A, density_per_A3: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(B,) bin centres (Å) and (B,) the radial distribution ``g(r)`` of (N, 3) positions: each
    bin's pair count over what a uniform gas of the same number density would hold
    (``N rho 4 pi r^2 dr / 2``; the density from the atoms' convex hull, :func:`number_density`).
    A finite particle's ``g`` falls below 1 at large ``r`` (its surface): read the shells' places,
    not their heights.  ``density_per_A3``: that density, where the caller has it."""
    positions = np.asarray(positions_A, dtype=np.float64).reshape(-1, 3)
    edges = np.arange(0.0, r_max_A + bin_A, bin_A)
    centres = 0.5 * (edges[1:] + edges[:-1])
    rho = number_density(positions) if density_per_A3 is None else density_per_A3
    if len(positions) < 2 or not rho > 0:
        return centres, np.zeros(len(centres))
    pairs = cKDTree(positions).query_pairs(r_max_A, output_type="ndarray")
    d = np.linalg.norm(positions[pairs[:, 0]] - positions[pairs[:, 1]], axis=1)
    counts = np.histogram(d, edges)[0]
    shell = 4.0 / 3.0 * math.pi * (edges[1:] ** 3 - edges[:-1] ** 3)
    return centres, counts / (0.5 * len(positions) * rho * shell)


def number_density(positions_A: np.ndarray) -> float:
    """Atoms per Å³ inside the convex hull of (N, 3) positions (0 for fewer than 4 or a flat set)."""
    positions = np.asarray(positions_A, dtype=np.float64).reshape(-1, 3)
    if len(positions) < 4:
        return 0.0
    try:
        volume = ConvexHull(positions).volume
    except QhullError:
        return 0.0
    return len(positions) / volume if volume > 0 else 0.0


def structure_evidence(positions_A: np.ndarray, hard_core_A: float) -> tuple[dict, np.ndarray, np.ndarray]:
    """The summary of :mod:`this module <.structure_evidence>` for (N, 3) reported atoms:
    ``n_atoms``, ``number_density_per_A3``, ``hard_core_A``, ``share_under_hard_core`` (atoms
    with a neighbour closer than it), ``nearest_neighbour_median_A``, and ``first_shell_peak_A``
    (the maximum of ``g(r)`` beyond the hard core); and the (B,) ``r`` and ``g(r)`` it read that
    from (:func:`pair_distribution_function`, for ``rdf.png``)."""
    from gaussian_atoms_method.atoms.hard_core import share_closer
    from gaussian_atoms_method.atoms.pair_distribution import nearest_neighbour_distances

    positions = np.asarray(positions_A, dtype=np.float64).reshape(-1, 3)
    rho = number_density(positions)
    out = {
        "n_atoms": len(positions),
        "number_density_per_A3": rho,
        "hard_core_A": float(hard_core_A) if math.isfinite(hard_core_A) else None,
    }
    out["share_under_hard_core"] = share_closer(positions, hard_core_A) if math.isfinite(hard_core_A) else None
    out["nearest_neighbour_median_A"] = (
        float(np.median(nearest_neighbour_distances(positions))) if len(positions) >= 2 else None
    )
    r, g = pair_distribution_function(positions, density_per_A3=rho)
    beyond = r > (hard_core_A if math.isfinite(hard_core_A) else 0.0)
    out["first_shell_peak_A"] = float(r[beyond][np.argmax(g[beyond])]) if np.any(g[beyond] > 0) else None
    return out, r, g
