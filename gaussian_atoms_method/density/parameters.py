"""The Gaussians' parameters as density control reads them: the parameter and optimiser
mappings, widths and amplitudes from their logarithms, and the mass levels the rules share."""

from __future__ import annotations

import math
from typing import Mapping, MutableMapping

import torch

Params = MutableMapping[str, torch.nn.Parameter]
TRAINING_SIGNIFICANCE = 1.0
"""During training a Gaussian goes once its mass is within one standard deviation of zero:
indistinguishable from nothing (:meth:`DensityControl.prune`)."""
Optimizers = Mapping[str, torch.optim.Optimizer]


SPLIT_MASS = 1.5
"""A Gaussian holding more than this many typical atoms' mass may hold two atoms: halfway
between one and two (:func:`split_worth`'s ceiling; a close pair heavier than this is two atoms
in :meth:`DensityControl.join_close_pairs`)."""

SINGLE_ATOM_Z = 1.96
"""How far above a typical atom, in the single atoms' own mass scatter, a Gaussian's mass must lie
before it is proposed for a split (:func:`split_worth`): the two-sided 95% level the run's
intervals use.  A proposal costs little, the final likelihood merge takes back every split the
data prefer as one."""


def median_and_scatter(values: torch.Tensor) -> tuple[float, float]:
    """The (N,) ``values``' median and robust scatter (interquartile range / 1.349: a normal's
    standard deviation), in float64 on the host.

    >>> [round(v, 4) for v in median_and_scatter(torch.tensor([0.8, 0.9, 1.0, 1.1, 1.2]))]
    [1.0, 0.1483]
    """
    q = torch.quantile(values.detach().double().cpu(), torch.tensor([0.25, 0.5, 0.75], dtype=torch.float64))
    return float(q[1]), float(q[2] - q[0]) / 1.349


def split_worth(worth: torch.Tensor) -> float:
    """The mass, in typical atoms, above which a Gaussian may hold more than one atom: a typical
    atom plus :data:`SINGLE_ATOM_Z` times the robust scatter of (N,) ``worth`` (the atom-like
    Gaussians' masses in typical atoms; interquartile range / 1.349), at most :data:`SPLIT_MASS`.

    Why: a Gaussian that took an atom and part of a neighbour along the beam is heavier than the
    single atoms by less than half an atom.  On the 76,000-atom a-Pd particle the Gaussian nearest
    a missed atom held a median 1.33 atoms' mass, above the single atoms' scatter (0.13) and
    below 1.5.  Where the masses spread wide (several species) the ceiling keeps halfway between
    one and two.

    >>> round(split_worth(torch.tensor([0.8, 0.9, 1.0, 1.1, 1.2])), 3)
    1.291
    """
    if worth.numel() < 4:
        return SPLIT_MASS
    return min(SPLIT_MASS, 1.0 + SINGLE_ATOM_Z * median_and_scatter(worth)[1])


def split_width(sigmas: torch.Tensor) -> float:
    """The width above which an atom-like Gaussian may hold two atoms: the (N,) ``sigmas``' median
    plus :func:`~gaussian_atoms_method.atoms.evidence.proof_level` (N) times their robust scatter
    (interquartile range / 1.349), so that among N single atoms none would reach it by chance
    with the family-wise error of a proof; infinite for fewer than 4.

    Why: through one microscope every atom is imaged at about one width (the probe's blur
    dominates it), whatever its element, so two atoms one Gaussian holds show as a width, where
    their mass may look like one heavier atom's (two Ni atoms along the beam as one Pd).  On a
    2,000-atom Ni-Pd-Pt particle through ADF physics the split took found from 0.991 to 0.9945
    and the elements right from 0.985 to 0.997.

    >>> round(split_width(torch.tensor([0.56, 0.58, 0.58, 0.60] * 25)), 3)
    0.604
    """
    from gaussian_atoms_method.atoms.evidence import proof_level

    if sigmas.numel() < 4:
        return math.inf
    median, scatter = median_and_scatter(sigmas)
    return median + proof_level(sigmas.numel()) * scatter


def widths(params: Mapping[str, torch.Tensor], min_log_sigma: float) -> torch.Tensor:
    """(N,) widths ``exp(log_sigma)`` floored at ``exp(min_log_sigma)``; with three widths (the
    anisotropic ablation) their geometric mean (same volume, same mass)."""
    return torch.exp(params["log_sigmas"].clamp_min(min_log_sigma).mean(dim=-1))


def amplitudes(params: Mapping[str, torch.Tensor]) -> torch.Tensor:
    """(N,) 3D peaks ``exp(log_amplitude)`` (the exponential keeps them positive)."""
    return torch.exp(params["log_amplitudes"]).squeeze(-1)
