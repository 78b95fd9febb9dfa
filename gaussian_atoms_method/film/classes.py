"""One material across a film: every sub-area's Gaussians split into atoms and non-atoms by one
class decision over all of them.

A run decides alone which of its Gaussians are atoms
(:func:`~gaussian_atoms_method.atoms.classification.classify_gaussians`): a mixture of (log mass,
log width) over its thousand or so Gaussians, and a class whose members mostly lie away from the
confident atoms is reported as non-atoms, whole.  On the Ta film the fitted masses form a
continuum, and a change of the fit at the rounding level moves its mixture between two classes and
three: of sub-area 23's two fits one dropped a light class (3-6% of it on a model atom) and the
other kept it, 0.137 against 0.276 extra atoms per model atom (``docs/studies/overlap_disagreement.md``).
Overlapping sub-areas then disagree on the atoms one set apart and the other did not.

The sub-areas are one material, so here the mixture is fitted once over all their Gaussians
within their detectors' extent, the confident class is the one that holds the most mass over the
film, and a class is apart where more than half of all its members, each judged in its own
sub-area (:func:`~gaussian_atoms_method.atoms.classification.near_confident`), lie away from the
confident atoms.  Each sub-area then keeps its supported Gaussians of the other classes, less those
within the hard core of a kept one that carries more mass
(:func:`~gaussian_atoms_method.atoms.hard_core.most_apart`), as a run does.  On the Ta film's
strips (the sub-areas' own fits as they were) the overlapping fits' median agreement rises from
0.781 to 0.814 (strip 1) and from 0.821 to 0.874 (strip 2).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gaussian_atoms_method.atoms.atom_set import read_atoms
from gaussian_atoms_method.atoms.classification import (
    confident_class,
    in_support,
    mixture_classes,
    near_confident,
)
from gaussian_atoms_method.atoms.hard_core import most_apart

NON_ATOMS_FILE = "non_atoms.xyz"
"""The run's non-atoms, beside its atoms (:func:`~gaussian_atoms_method.engine.results.write_results`)."""


@dataclass
class SubAreaGaussians:
    """One sub-area's Gaussians within its detector's extent across the beam, in its own frame:
    ``positions`` (N, 3) Å, ``sigmas_A`` and ``masses`` (N,), ``position_std_A`` (N, 3),
    ``trusted`` (N,) bool (a non-atom is not; None where the run does not say) and whether the
    run reported each as an atom, ``reported`` (N,) bool."""

    positions: np.ndarray
    sigmas_A: np.ndarray
    masses: np.ndarray
    position_std_A: np.ndarray
    trusted: np.ndarray | None
    reported: np.ndarray


def read_gaussians(atoms_path: Path, subarea) -> SubAreaGaussians | None:
    """The Gaussians of the run whose atoms are ``atoms_path`` (its non-atoms beside them), those
    within the detector of ``subarea`` (:class:`~.subareas.SubArea`) across the beam; None where
    the run wrote no non-atoms or no widths, masses and precisions."""
    atoms_path = Path(atoms_path)
    rest_path = atoms_path.parent / NON_ATOMS_FILE
    if not rest_path.is_file():
        return None
    atoms, rest = read_atoms(atoms_path), read_atoms(rest_path)
    parts = (atoms, rest)
    if any(p.masses is None or p.position_std_A is None for p in parts if len(p)):
        return None
    # the detector in the sub-area's own frame: its interior with no edge, at no offset
    lo, hi = dataclasses.replace(subarea, offset_A=(0.0, 0.0, 0.0), edge_px=(0, 0)).interior_A

    def stacked(get, width: int) -> np.ndarray:
        blocks = [np.asarray(get(p), np.float64).reshape(len(p), width) for p in parts if len(p)]
        return np.concatenate(blocks or [np.zeros((0, width))])

    positions = stacked(lambda p: p.positions, 3)
    within = np.all((positions[:, :2] >= lo) & (positions[:, :2] <= hi), axis=1)
    trusted = None
    if atoms.trusted is not None or not len(atoms):
        said = np.asarray(atoms.trusted, np.float64) > 0 if len(atoms) else np.zeros(0, bool)
        trusted = np.r_[said, np.zeros(len(rest), bool)][within]
    return SubAreaGaussians(
        positions[within],
        stacked(lambda p: p.sigmas, 1)[:, 0][within],
        stacked(lambda p: p.masses, 1)[:, 0][within],
        stacked(lambda p: p.position_std_A, 3)[within],
        trusted,
        np.r_[np.ones(len(atoms), bool), np.zeros(len(rest), bool)][within],
    )


@dataclass
class FilmSplit:
    """The film's decision: per sub-area the Gaussians it keeps as atoms (``kept``, (N,) bool
    each), the classes apart (``apart``) of the ``n_classes`` fitted over ``n_gaussians``."""

    kept: list[np.ndarray]
    apart: list[int]
    n_classes: int
    n_gaussians: int

    def words(self, sets: list[SubAreaGaussians]) -> str:
        """The decision and what it changed against the runs' own, in a sentence."""
        dropped = sum(int((g.reported & ~k).sum()) for g, k in zip(sets, self.kept))
        added = sum(int((~g.reported & k).sum()) for g, k in zip(sets, self.kept))
        apart = ", ".join(f"class {c}" for c in self.apart) or "none"
        return (
            f"one class decision over the {len(sets)} sub-areas' {self.n_gaussians:,} Gaussians ({self.n_classes} "
            f"classes by mass and width; apart from the atoms: {apart}): {dropped} Gaussians the sub-areas' fits "
            f"reported are non-atoms of the film, {added} they had set apart are its atoms"
        )


def film_split(sets: list[SubAreaGaussians], hard_core_A: float, device="cpu") -> FilmSplit:
    """Every sub-area's Gaussians of ``sets`` split by one class decision over all of them (module
    text), ``hard_core_A`` apart within each sub-area (none where it is not finite); the mixture
    is fitted on ``device``.

    >>> rng = np.random.default_rng(0)
    >>> grid = np.stack(np.meshgrid(*[np.arange(0.0, 24.0, 2.8)] * 3, indexing="ij"), -1).reshape(-1, 3)
    >>> layer = np.c_[rng.uniform(0, 22, (60, 2)), rng.uniform(30, 34, 60)]  # light and wide, above
    >>> def fitted(reported_layer):
    ...     positions = np.r_[grid, layer]
    ...     n, m = len(grid), len(layer)
    ...     return SubAreaGaussians(positions, np.r_[np.full(n, 0.6), np.full(m, 0.9)],
    ...         np.exp(np.r_[rng.normal(0, 0.05, n), rng.normal(-1, 0.05, m)]), np.full((n + m, 3), 0.01),
    ...         None, np.r_[np.ones(n, bool), np.full(m, reported_layer)])
    >>> split = film_split([fitted(True), fitted(False)], 2.2)
    >>> [int(k.sum()) for k in split.kept], len(grid), split.n_classes
    ([729, 729], 729, 2)
    """
    sizes = [len(g.masses) for g in sets]
    masses = np.concatenate([g.masses for g in sets])
    if len(masses) == 0:
        return FilmSplit([np.zeros(0, bool) for _ in sets], [], 0, 0)
    classes, means, _ = mixture_classes(masses, np.concatenate([g.sigmas_A for g in sets]), device=device)
    own = np.split(classes, np.cumsum(sizes)[:-1])
    supports = [in_support(g.positions) for g in sets]
    confident = confident_class(classes, np.concatenate(supports), masses)
    apart: list[int] = []
    if confident is not None:
        near = [near_confident(c, s, g.positions, confident) for g, c, s in zip(sets, own, supports)]
        judged = [(c, n) for c, n in zip(own, near) if n is not None]
        for label in np.unique(classes):
            members = np.concatenate([n[c == label] for c, n in judged] or [np.zeros(0, bool)])
            if label != confident and len(members) and members.mean() < 0.5:
                apart.append(int(label))
    kept = []
    for g, c, s in zip(sets, own, supports):
        keep = s & ~np.isin(c, apart)
        if np.isfinite(hard_core_A) and keep.any():
            within = np.flatnonzero(keep)
            keep[within[~most_apart(g.positions[within], hard_core_A, g.masses[within])]] = False
        kept.append(keep)
    return FilmSplit(kept, apart, len(means), len(masses))
