"""The Gaussians' parameters as density control reads them: the parameter and optimiser
mappings, widths and amplitudes from their logarithms, and the mass levels the rules share."""

from __future__ import annotations

from typing import Mapping, MutableMapping

import torch

Params = MutableMapping[str, torch.nn.Parameter]
TRAINING_SIGNIFICANCE = 1.0
"""During training a Gaussian goes once its mass is within one standard deviation of zero:
indistinguishable from nothing (:meth:`DensityControl.prune`)."""
Optimizers = Mapping[str, torch.optim.Optimizer]


SPLIT_MASS = 1.5
"""A Gaussian holding more than this many typical atoms' mass may hold two atoms: halfway
between one and two (:meth:`DensityControl.split_heavy_gaussians`; the final likelihood merge
decides)."""


def widths(params: Mapping[str, torch.Tensor], min_log_sigma: float) -> torch.Tensor:
    """(N,) widths ``exp(log_sigma)`` floored at ``exp(min_log_sigma)``; with three widths (the
    anisotropic ablation) their geometric mean (same volume, same mass)."""
    return torch.exp(params["log_sigmas"].clamp_min(min_log_sigma).mean(dim=-1))


def amplitudes(params: Mapping[str, torch.Tensor]) -> torch.Tensor:
    """(N,) 3D peaks ``exp(log_amplitude)`` (the exponential keeps them positive)."""
    return torch.exp(params["log_amplitudes"]).squeeze(-1)
