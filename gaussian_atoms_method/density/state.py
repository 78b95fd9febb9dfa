"""What density control keeps between steps, apart from its settings (as gsplat's strategies
keep a state dict apart from their settings): the gradients and iterates of the open refine
interval, each Gaussian's birth step, where the residual searches stand, and the run's counts
for its report."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from gaussian_atoms_method.density.averaging import IterateAverage


@dataclass
class DensityState:
    """The running state of :class:`~gaussian_atoms_method.density.strategy.DensityControl`."""

    grad_accum: torch.Tensor = field(default_factory=lambda: torch.zeros(0, 3))
    """(N, 3) sum of the means' gradient vectors since the last refine (CPU)."""
    grad_count: int = 0
    average: IterateAverage = field(default_factory=IterateAverage)
    """The iterates of the open refine interval (:mod:`.averaging`)."""
    born: torch.Tensor = field(default_factory=lambda: torch.zeros(0, dtype=torch.long))
    """(N,) step at which each Gaussian was made (0 for the start); fresh ones are not merged."""
    founded: torch.Tensor = field(default_factory=lambda: torch.zeros(0, dtype=torch.long))
    """(N,) step at which each Gaussian's oldest member was made (a merged Gaussian is as old as
    its oldest member, a copy as new as its making): what is left of a search's additions is
    what holds none of the Gaussians before it (:meth:`.DensityControl.descendants`)."""
    step: int = 0
    residual_clean: bool = False
    """A residual check found nothing to add: the later ones are skipped."""
    searched_at: int = 0
    """The step of the last residual search that added Gaussians (0: none yet)."""
    settled_since_search: bool = False
    """The final rules were applied mid-run since that search (:meth:`.DensityControl.settle`)."""
    addition_masses: tuple | None = None
    """(search step, (K, 3) positions, (K,) masses) of that search's Gaussians at the last check
    (:meth:`.DensityControl.additions_settled`)."""
    hard_core_read: tuple = (0, math.inf)
    """The last reading from the atoms: (Gaussians then, hard core normalised)."""
    joined_close: int = 0
    """Gaussians joined into a partner closer than the hard core over the run
    (:meth:`.DensityControl.join_close_pairs`)."""
    heavy_split: bool = False
    """The heavy Gaussians were split (:meth:`.DensityControl.split_heavy_gaussians`: once a run)."""
    clamp_counts: torch.Tensor | None = None
    """(4,) Gaussian-steps held at the width floor, the width ceiling, the amplitude ceiling and
    the edge of the position box (kept on the parameters' device: no sync per step)."""
    pruned_outside: int = 0
    """Gaussians pruned for leaving the reconstruction volume ..."""
    leavers: list = field(default_factory=list)
    """... of which those above the field that training would have kept: (mass, width) CPU
    tensors, normalised, judged at the run's end (:meth:`.DensityControl.atom_like_leavers`)."""
    boxes: dict = field(default_factory=dict, repr=False)
    """The position boxes as tensors, per device and dtype (:meth:`.DensityControl._box`)."""
