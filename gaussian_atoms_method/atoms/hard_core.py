"""The material's hard core: the distance no two of its atoms come closer than.

Gaussians are the model; atoms are the report, and two atoms closer than the material allows
have zero prior probability.  The distance comes from one of two places:

* **species given** (``Ta``, ``Fe,Pt``): :data:`COVALENT_FRACTION` of the sum of the two
  elements' single-bond covalent radii (B. Cordero et al., "Covalent radii revisited", Dalton
  Trans. 2832 (2008), as ``ase.data.covalent_radii`` tabulates them), the least over the
  material's pairs of elements (:func:`hard_core_from_species`);
* **read from the data**: :data:`SHELL_FRACTION` of the typical bond of the confident heavy
  atoms, the peak of their first coordination shell
  (:func:`hard_core_from_positions`, :func:`..atoms.pair_distribution.first_shell`).

Both fractions start from the shortest bond chemistry knows: the Cr-Cr quintuple bond, 1.73-1.80 Å,
is 0.62-0.65 of Cordero's 2.78 Å and 0.69-0.72 of bcc Cr's 2.50 Å nearest neighbours (the C≡C
triple bond, 1.20 Å, is 0.79 and 0.85 of the same).  A measured pair's distance carries both
atoms' position errors; 0.07 of the bond is left for them (0.18 Å of a 2.6 Å metal bond: one
standard deviation of the distance between two positions each known to 13 pm along it).  Tantalum: 1.87 Å
from its species (Ta-Ta bonds 2.5-3.0 Å); gold 1.50 Å; silicon 1.22 Å; carbon 0.84 Å.

Pure numpy (and ASE's table on first use).
"""

from __future__ import annotations

import math
import re
from typing import Sequence

import numpy as np

SHORTEST_BOND_OF_RADII = 0.62
"""The shortest bond known (Cr-Cr quintuple, 1.73 Å) over the sum of its elements' covalent radii."""
SHORTEST_BOND_OF_SHELL = 0.69
"""The same bond over its element's ordinary bond (bcc Cr, 2.50 Å)."""
POSITION_ALLOWANCE = 0.07
"""What a measured pair's distance may fall short of the true one, as a fraction of the bond."""
COVALENT_FRACTION = SHORTEST_BOND_OF_RADII - POSITION_ALLOWANCE
"""Hard core over the sum of the covalent radii (0.55)."""
SHELL_FRACTION = SHORTEST_BOND_OF_SHELL - POSITION_ALLOWANCE
"""Hard core over the first shell's peak read from the atoms (0.62)."""
HEAVY_FRACTION = 0.5
"""The data's reading uses Gaussians holding at least this share of a typical atom's mass: a pair
the fit made shares one atom's mass, so at most one of its partners counts."""


class SpeciesError(ValueError):
    """A species list that names no element, or an unknown one; the message names it."""


def parse_species(species: str | Sequence[str] | None) -> tuple[str, ...]:
    """The element symbols of ``species`` ("Ta", "Fe,Pt", "Fe Pt" or a sequence), in the
    order given, without repeats; () for None or an empty string.  Raises :class:`SpeciesError`
    naming an unknown symbol."""
    if species is None:
        return ()
    names = re.split(r"[,\s]+", species.strip()) if isinstance(species, str) else [str(s).strip() for s in species]
    out: list[str] = []
    for name in names:
        if not name:
            continue
        symbol = name[:1].upper() + name[1:].lower()
        if symbol not in _radii():
            raise SpeciesError(f"species: unknown element {name!r}; expected chemical symbols such as Ta or Fe,Pt")
        if symbol not in out:
            out.append(symbol)
    return tuple(out)


def _radii() -> dict[str, float]:
    from ase.data import atomic_numbers, covalent_radii

    return {s: float(covalent_radii[z]) for s, z in atomic_numbers.items() if 0 < z < len(covalent_radii)}


def hard_core_from_species(species: str | Sequence[str]) -> float:
    """The hard core of a material of these elements, Å: :data:`COVALENT_FRACTION` of the least
    sum of two covalent radii among its pairs of elements (an element with itself included)."""
    return COVALENT_FRACTION * _least_radii_sum(species)


def shortest_bond_from_species(species: str | Sequence[str]) -> float:
    """The shortest distance two atoms of a material of these elements can be apart, Å:
    :data:`SHORTEST_BOND_OF_RADII` of the least sum of two covalent radii among its pairs of
    elements (2.11 Å for tantalum, whose bonds are 2.5-3.0 Å).  The hard core is this less
    :data:`POSITION_ALLOWANCE`, the room a measured pair's distance needs; a specimen's true
    atoms need none (:func:`~gaussian_atoms_method.harness.replica.physical_truth`).

    >>> round(shortest_bond_from_species("Ta"), 2), round(hard_core_from_species("Ta"), 2)
    (2.11, 1.87)
    """
    return SHORTEST_BOND_OF_RADII * _least_radii_sum(species)


def _least_radii_sum(species: str | Sequence[str]) -> float:
    """The least sum of two covalent radii among the pairs of ``species``' elements, Å."""
    elements = parse_species(species)
    if not elements:
        raise SpeciesError("species: name at least one element, e.g. Ta or Fe,Pt")
    radii = _radii()
    return 2.0 * min(radii[e] for e in elements)


def hard_core_from_positions(positions: np.ndarray, masses: np.ndarray, typical_mass: float) -> tuple[float, float]:
    """The hard core read from (N, 3) confident atoms with (N,) masses: :data:`SHELL_FRACTION` of
    their typical bond.  Only the heavy ones count (:data:`HEAVY_FRACTION` of ``typical_mass``).
    The bond is their first shell's peak; where most nearest neighbours lie far below it (another
    shell is below the main peak), their median nearest-neighbour distance.  Returns (hard core,
    bond), both infinite with too few heavy atoms (:data:`..atoms.pair_distribution.MIN_ATOMS`)."""
    from gaussian_atoms_method.atoms.pair_distribution import first_shell, nearest_neighbour_distances

    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    heavy = positions[np.asarray(masses) >= HEAVY_FRACTION * typical_mass]
    shell = first_shell(heavy)
    if not math.isfinite(shell.peak):
        return math.inf, math.inf
    bond = shell.peak if shell.inner_share < 0.5 else float(np.median(nearest_neighbour_distances(heavy)))
    return SHELL_FRACTION * bond, bond


def close_pairs(positions: np.ndarray, distance: float) -> np.ndarray:
    """(K, 2) index pairs of (N, 3) positions closer than ``distance``, closest first."""
    from scipy.spatial import cKDTree

    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    if len(positions) < 2 or not distance > 0 or not math.isfinite(distance):
        return np.zeros((0, 2), dtype=np.int64)
    pairs = cKDTree(positions).query_pairs(distance, output_type="ndarray")
    if len(pairs) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    d = np.linalg.norm(positions[pairs[:, 0]] - positions[pairs[:, 1]], axis=1)
    keep = d < distance
    return pairs[keep][np.argsort(d[keep], kind="stable")]


def share_closer(positions: np.ndarray, distance: float) -> float:
    """Share of (N, 3) positions with a neighbour closer than ``distance`` (0 with fewer than two)."""
    from gaussian_atoms_method.atoms.pair_distribution import nearest_neighbour_distances

    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    if len(positions) < 2:
        return 0.0
    return float(np.mean(nearest_neighbour_distances(positions) < distance))


def most_apart(positions: np.ndarray, distance: float, weights: np.ndarray | None = None) -> np.ndarray:
    """(N,) bool: the most of (N, 3) ``positions`` with no two closer than ``distance``: of each
    group of points joined by closer pairs, its largest subset with no such pair (every subset
    where the group has at most 16 points, as a measured model's close pairs come in twos and
    threes; else the least-joined point first, greedily).  What a report that obeys the hard core
    can hold of an atom set where the set puts its atoms; the rest lie within another's core.

    With (N,) ``weights``, the subset of the greatest total weight (greedily: the heaviest first):
    given the Gaussians' masses, what the report holds as atoms of Gaussians closer than the hard
    core, the most mass it can hold.  Of a pair, the heavier; of a wide Gaussian between two
    atoms 2.7 Å apart, each 1.3-1.6 Å from it (one atom's mass, the others 0.8-0.9), the two
    (a replica of Ta sub-area 25: they were its misses, the wide one false).

    >>> chain = np.array([[0.0, 0, 0], [1.5, 0, 0], [3.0, 0, 0], [10.0, 0, 0]])
    >>> most_apart(chain, 1.87)  # a chain of three keeps its two ends
    array([ True, False,  True,  True])
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    keep = np.ones(len(positions), dtype=bool)
    pairs = close_pairs(positions, distance)
    if not len(pairs):
        return keep
    weights = None if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(positions),) * 2)
    _, group = connected_components(graph, directed=False)
    slot = np.zeros(len(positions), dtype=np.int64)  # each point's index within its group
    for g in np.unique(group[pairs[:, 0]]):
        members = np.flatnonzero(group == g)
        slot[members] = np.arange(len(members))
        edges = slot[pairs[group[pairs[:, 0]] == g]]
        keep[members] = _largest_apart(len(members), edges, None if weights is None else weights[members])
    return keep


def _largest_apart(n: int, edges: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """(n,) bool: the most of ``n`` points (the greatest total of ``weights``) with no two joined
    by one of the (K, 2) ``edges``."""
    a, b = np.asarray(edges, dtype=np.int64).T
    if n <= 16:
        masks = np.arange(1 << n)
        allowed = ~np.any((masks[:, None] >> a & 1) & (masks[:, None] >> b & 1), axis=1)
        chosen = (masks[:, None] >> np.arange(n) & 1).astype(bool)
        sizes = chosen.sum(axis=1) if weights is None else chosen @ weights
        return chosen[np.flatnonzero(allowed & (sizes == sizes[allowed].max()))[0]]
    left, kept = np.ones(n, dtype=bool), np.zeros(n, dtype=bool)
    while left.any():
        live = left[a] & left[b]
        degree = np.bincount(a[live], minlength=n) + np.bincount(b[live], minlength=n)
        order = degree[left] if weights is None else -weights[left]
        point = int(np.flatnonzero(left)[np.argmin(order)])
        kept[point] = True
        left[point] = False
        left[np.r_[b[a == point], a[b == point]]] = False
    return kept
