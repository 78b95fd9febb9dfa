"""Density control's settings, declared once: :class:`DensitySettings`.

The fit's options (:class:`gaussian_atoms_method.engine.options.FitOptions`, the command line's
``--pipeline.model.*``) and the density control
(:class:`gaussian_atoms_method.density.strategy.DensityControl`) both are these settings, by
inheritance: a setting renamed here is renamed in both, and each field's string says what it
does and where its value comes from (``--help`` shows it).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


@dataclass
class DensitySettings:
    """How many Gaussians there are, and where: widths, the schedule of the duplicate, prune and
    merge rules, and the false alarms and discoveries accepted (lengths in Å)."""

    min_sigma_A: float = 0.15
    """Floor on the width, Å: no atom (after probe blur) is narrower; keeps the fit finite."""
    max_atom_sigma_A: float = 1.5
    """Gaussians wider than this (Å) are not atoms (an atom blurred by a 0.5 Å probe is about
    0.6 Å wide): they are pruned and left out of the typical atom mass."""
    max_sigma_A: float = 5.0
    """Ceiling on the width, Å: far wider than any atom; keeps a runaway Gaussian finite."""
    warmup_length: int = 200
    """Steps before the first densify / prune / merge."""
    refine_every: int = 100
    """Steps between densify / prune / merge."""
    stop_split_at: int = 2500
    """No more duplication after this step (pruning and merging continue)."""
    densify_grad_thresh: float = 0.2
    """Duplicate Gaussians whose mean positional gradient (norm of the average gradient vector
    over a refine interval, normalised units) exceeds this.  Measured on the demo data, a
    fitted atom's sits at 0.02-0.1 (L1 noise), so 0.2 only duplicates under a persistent pull.
    The paper's 0.005 is on gsplat's screen-space scale and would duplicate everything here."""
    max_gaussians: int = 200000
    """Never hold more Gaussians than this."""
    prune_mass_fraction: float = 0.25
    """Only where the noise is unknown (a model built without a tilt series): prune Gaussians
    whose integrated mass is below this fraction of a typical atom's (the mass-weighted median
    mass).  With data, the prune is by significance (false_alarm_rate)."""
    false_alarm_rate: float = 0.05
    """Chance that a noise blob anywhere in the volume survives the prune: a Gaussian stays
    while its mass over its Cramér-Rao standard deviation (in the measured noise) exceeds the
    normal quantile at this rate shared over the volume's 1 Å^3 cells
    (:meth:`gaussian_atoms_method.density.strategy.DensityControl.significance_threshold`;
    4.5 sigma for a 25 Å box at 5%)."""
    false_discovery_rate: float = 0.001
    """The final prune keeps the Gaussians whose mass significance clears the Benjamini-Hochberg
    level at this rate (noise Gaussians expected among those kept: at most this fraction), never
    stricter than the false_alarm_rate level
    (:meth:`gaussian_atoms_method.density.strategy.DensityControl.discovery_threshold`).  0.001:
    one in a thousand, ten times below the 0.01 false atoms per atom the benchmarks ask for, so
    noise never dominates the false atoms (at Au noise 500 the rates 0.0005-0.005 gave the same
    false atoms: fragments of atoms, not noise)."""
    add_from_residuals: bool = True
    """Once the atoms are settled (the convergence check), back-project the residuals of every
    view and add a Gaussian wherever they hold significant unexplained mass
    (:mod:`gaussian_atoms_method.atoms.residual_sites`: above the level a noise peak reaches in
    the volume with chance false_alarm_rate), then train on; stop only when a search finds
    nothing (or at stop_split_at).  Each search costs a rendering of every view and two
    back-projections.  Searching earlier, every 500 steps, also added Gaussians at the
    unsettled atoms' misfit (29 on the demo, which has no atom missing) and kept the
    convergence check from stopping."""
    split_heavy: bool = True
    """At the first residual search, split each Gaussian heavier than the single atoms' mass
    range (:func:`gaussian_atoms_method.density.parameters.split_worth`, at most 1.5 typical
    atoms) into two, the material's shortest distance apart along the least-resolved direction
    (:meth:`gaussian_atoms_method.density.strategy.DensityControl.split_heavy_gaussians`: in a
    thick particle one Gaussian can hold two atoms along the beam); the final likelihood merge
    rejoins any the data prefer as one, and any pair that is one peak with one atom's mass."""
    isotropic: bool = True
    """One width per Gaussian (the isotropy prior).  False: three widths and a rotation each."""
    average_iterates: bool = True
    """The Gaussians' estimate is the mean of the optimiser's iterates over each refine interval,
    written into them when it closes and at the end (Polyak-Ruppert averaging,
    :mod:`gaussian_atoms_method.density.averaging`): one-view steps jitter the atoms by more than
    the data's precision, and the mean cancels that.  False: the last iterate."""
    cluster_merge: bool = True
    """Merge Gaussians closer than merge_threshold_A (the minimum-distance prior)."""
    merge_every: int = 100
    """Steps between cluster merges (after the warm-up)."""
    merge_threshold_A: float = 0.7
    """Gaussians closer than this (Å) merge into one."""
    merge_amplitude: Literal["mass", "mean"] = "mass"
    """Amplitude of a merged Gaussian: conserve the summed mass, or the mean amplitude (paper)."""
