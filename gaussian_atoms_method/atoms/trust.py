"""Which atoms to trust: each reason a run leaves an atom open, and the line that says them.

An atom is open where its evidence (:mod:`.evidence`, :mod:`.calibration`) leaves it in doubt:
not proven, open in depth (also where the views fix its depth far less well than its element's
atoms', :func:`depth_unlike_its_element`), wider than one atom, of a mass unlike one atom of its
element (:func:`mass_unlike_one_atom`), or open in element.  ``trusted`` in ``atoms.csv`` is the rest.
"""

from __future__ import annotations

import numpy as np

MIN_MASS_REFERENCE = 10
"""An element's mass population is its own reference where it has at least this many atoms (as
:data:`.calibration.MIN_WIDTH_REFERENCE` for widths); else all atoms'."""


def beyond_population(log_values, level: float, species=None, below_only: bool = False) -> np.ndarray:
    """(N,) bool: the value (on a log scale, (N,)) lies beyond its element's population by more
    than ``level`` times that population's spread (median, and 1.4826 times the median absolute
    deviation: a normal's standard deviation that the outliers do not widen); ``below_only``: on
    the low side only.  An element with at least :data:`MIN_MASS_REFERENCE` atoms is its own
    population; the rest are pooled.  NaN values are neither open nor part of a population.

    >>> beyond_population(np.log([1.0, 1.05, 0.95, 1.02, 0.98, 2.0, 0.4]), 4.0, below_only=True).tolist()
    [False, False, False, False, False, False, True]
    """
    log_values = np.asarray(log_values, dtype=np.float64)
    groups = [np.ones(log_values.shape, bool)]
    if species is not None:
        species = np.asarray(species)
        own = [species == e for e in np.unique(species) if np.sum(species == e) >= MIN_MASS_REFERENCE]
        rest = ~np.any(own, axis=0) if own else np.ones(log_values.shape, bool)
        groups = own + ([rest] if rest.any() else [])
    known = np.isfinite(log_values)
    unlike = np.zeros(log_values.shape, bool)
    for mine in groups:
        reference = log_values[mine & known] if np.sum(mine & known) >= MIN_MASS_REFERENCE else log_values[known]
        if not len(reference):
            continue
        median = np.median(reference)
        spread = 1.4826 * np.median(np.abs(reference - median))
        if spread <= 0:
            continue
        below = median - log_values[mine] > level * spread
        unlike[mine] = below if below_only else below | (log_values[mine] - median > level * spread)
    return unlike & known


def mass_unlike_one_atom(masses, level: float, species=None) -> np.ndarray:
    """(N,) bool: the atom's mass lies beyond its element's population by more than ``level``
    times that population's spread, on a log scale (:func:`beyond_population`).

    Why: one atom of an element projects one mass, scattered by the noise and by what its
    neighbours lend it, so a Gaussian far heavier holds two atoms (or a neighbour's mass along the
    beam) and one far lighter is part of an atom whose rest lies elsewhere.  ``level`` is the
    proof level (:func:`.evidence.proof_level`): by chance no single atom among as many reaches it.
    On the 54,000-atom Pd particle through ADF physics (fitted on a CPU), 68 of its 146 false
    atoms lay beyond it and 24 of its 53,863 right atoms.  NaN masses are not open.

    >>> mass_unlike_one_atom(np.array([1.0, 1.05, 0.95, 1.02, 0.98, 2.0]), 4.0).tolist()
    [False, False, False, False, False, True]
    """
    masses = np.asarray(masses, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        return beyond_population(np.log(np.clip(masses, 1e-300, None)), level, species)


def depth_unlike_its_element(
    depth_rise, level: float, species=None, depth_halfwidth_A=None, floor_z_A: float = 0.0
) -> np.ndarray:
    """(N,) bool: the views tell the atom's place along the beam from the best other place tried
    (``depth_rise`` (N,), :attr:`.evidence.AtomEvidence.depth_rise`) by far less than they do for
    the atoms of its element (its log rise below that population by more than ``level`` times
    its spread: :func:`beyond_population`, the low side), and not beyond doubt: the rise, read in
    the unit a floor ``floor_z_A`` along the beam widens the stated interval to
    ``depth_halfwidth_A`` (N,) in (:func:`.calibration.with_floor`), is under ``level^2``.

    Why: how much worse an atom fits one step along the beam is set by its mass, the tilt range
    and how crowded its column is, alike for the atoms of one element in one particle; an atom far
    below them sits where a column could shift, and the fit may have placed it wrong (a misfit
    alike in every view, which the residual that sets the stated unit does not show).  An other
    place worse by the proof level squared is excluded as firmly as an atom is proven, so such
    an atom stays closed however unlike the others.  ``level`` is the proof level.  On the
    54,000-atom Pd particle through ADF physics (fitted on a CPU) it opened 104 more of the 120
    false atoms and misses together, and 110 of 53,917 right atoms; on a 321-atom Au sphere the
    10 atoms below their population (rises of 1,600-2,300) stay closed.  Negative rises (a place
    the views prefer) are open; NaN is not.

    >>> depth_unlike_its_element(np.array([100.0, 90.0, 110.0, 105.0, 95.0, 12.0, np.nan]), 4.0).tolist()
    [False, False, False, False, False, True, False]
    >>> depth_unlike_its_element(np.array([1e4, 9e3, 1.1e4, 1.05e4, 9.5e3, 2e3]), 4.0).tolist()
    [False, False, False, False, False, False]
    """
    from gaussian_atoms_method.atoms.calibration import Z95

    rise = np.asarray(depth_rise, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        unlike = beyond_population(np.log(np.clip(rise, 1e-3, None)), level, species, below_only=True)
        unit = 1.0
        if depth_halfwidth_A is not None and floor_z_A:
            unit = np.clip(1.0 - (Z95 * floor_z_A / np.asarray(depth_halfwidth_A, dtype=np.float64)) ** 2, 0.0, 1.0)
        return unlike & (rise * unit < level**2)


def element_open(atoms) -> np.ndarray:
    """(N,) bool: the element written for each of ``atoms`` is open: its probability under
    :data:`~.species.ELEMENT_OPEN_BELOW`, or unknown (NaN: the masses could not tell the elements
    given apart); all False without ``element_confidence``."""
    from gaussian_atoms_method.atoms.species import ELEMENT_OPEN_BELOW

    if atoms.element_confidence is None:
        return np.zeros(len(atoms), bool)
    with np.errstate(invalid="ignore"):
        return ~(atoms.element_confidence >= ELEMENT_OPEN_BELOW)


def open_atoms(atoms) -> np.ndarray:
    """(N,) bool: the atoms a run leaves open (an :class:`~.atom_set.AtomSet` with its
    evidence): not proven, open in depth, wider than one atom, of a mass unlike one atom of its
    element, or open in element (:func:`element_open`); the columns it lacks open none."""
    is_open = (atoms.proven == 0) | (atoms.depth_open == 1) | element_open(atoms)
    for flag in (atoms.width_open, atoms.mass_open):
        if flag is not None:
            is_open |= flag == 1
    return is_open


def trust_words(atoms) -> str:
    """The run's one sentence on which of its ``atoms`` (an :class:`~.atom_set.AtomSet` with its
    evidence and ``info["proof_level"]``) to trust: how many nothing leaves open (``trusted``),
    and how many each reason leaves open (an atom may be open for several).

    >>> from gaussian_atoms_method.atoms.atom_set import AtomSet
    >>> atoms = AtomSet(np.zeros((3, 3)), proven=[1, 1, 0], depth_open=[0, 1, 0], info={"proof_level": 3.6},
    ...                 significance=[9.0, 8.0, 2.0])
    >>> trust_words(atoms)[:60]
    'trust 1 of 3 atoms (trusted 1 in atoms.csv: proven, closed i'
    """
    from gaussian_atoms_method.atoms.species import ELEMENT_OPEN_BELOW

    level = atoms.info["proof_level"]
    trusted = int(np.sum(~open_atoms(atoms)))
    parts = [
        f"{int(np.sum(atoms.proven == 0))} not proven (the views lose less than {level:.1f} noise standard "
        "deviations without them, their neighbours re-fitted)",
        f"{int(np.sum(atoms.depth_open == 1))} open in depth (95% interval along the beam wider than half the hard "
        f"core, another place there as good or better, or one fitting worse by far less than for its element's "
        f"atoms: log rise below their median by more than {level:.1f} times their spread, and under {level:.1f}^2)",
    ]
    if atoms.width_open is not None:
        parts.append(
            f"{int(np.sum(atoms.width_open == 1))} wider than one atom (may hold two: width above its element's "
            f"median by more than {level:.1f} times its precision)"
        )
    if atoms.mass_open is not None:
        parts.append(
            f"{int(np.sum(atoms.mass_open == 1))} of a mass unlike one atom of their element (may hold two, or part "
            f"of one: log mass beyond its element's median by more than {level:.1f} times their spread)"
        )
    several = atoms.element_confidence is not None and not np.all(atoms.element_confidence == 1)
    if several:
        parts.append(
            f"{int(element_open(atoms).sum())} open in element (probability under {ELEMENT_OPEN_BELOW:g}, or unknown)"
        )
    return (
        f"trust {trusted} of {len(atoms)} atoms (trusted 1 in atoms.csv: proven, closed in depth, one atom "
        f"wide{', element sure' if several else ''}); open: "
        + ", ".join(parts)
        + f"; median significance {np.median(atoms.significance):.1f}"
    )
