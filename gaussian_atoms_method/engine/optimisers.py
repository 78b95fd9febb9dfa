"""The fit's optimisers: one Adam per parameter group, each with its learning rate and schedule.

Rates are in normalised units (the detector's longer side is 1).  :data:`RATES` is the one
source: the engine's :class:`Optimisers` and nerfstudio's method config
(:mod:`gaussian_atoms_method.nerfstudio_layer.config`) are both built from it, and step alike
(nerfstudio's ``Optimizers``: the groups in the fit's order, Adam where a group has a gradient,
then every schedule).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, List

import numpy as np
import torch
from torch.optim import lr_scheduler


@dataclass(frozen=True)
class Rate:
    """Adam's rate ``lr`` for one group, decaying exponentially to ``lr_final`` over the
    schedule's steps (None: constant), with Adam's ``eps``."""

    lr: float
    lr_final: float | None = None
    eps: float = 1e-15


RATES: Dict[str, Rate] = {
    # decays tenfold over the run so that atoms settle to pm precision
    "means": Rate(1e-3, 1e-4),
    "log_sigmas": Rate(5e-3),
    "log_amplitudes": Rate(2e-2),
    # only with isotropic False (the ablation)
    "quats": Rate(1e-3),
    # the background is solved in closed form (floors.py); its group stays so that checkpoints
    # with its state load
    "background": Rate(1e-1),
    # the point-spread function's weights, shared by every view, move every step: 2e-3 takes a
    # weight from 0 to a fifth of the intensity in about 100 steps and leaves it within 0.2%
    "psf": Rate(2e-3),
    # refine-alignment (normalised lengths): a view's shift moves only on the steps that render
    # it (about 64 of 3,000 on a 47-view series); 2e-3 a step (0.14 Å on a 70 Å detector)
    # closes a 1 Å error in the first third of the run
    "view_shifts": Rate(2e-3, 1e-4),
    # refine-gain (log gain): like a shift, a view's gain moves on the steps that render it;
    # 2e-3 a step reaches a 7% gain in about 35 of them
    "view_gains": Rate(2e-3, 1e-4),
    # refine-tilts (radians; 5e-4 ~ 0.03 deg a step)
    "view_tilts": Rate(5e-4, 2e-5),
}
"""Each parameter group's rate and schedule."""


def adam(params, lr: float, eps: float, weight_decay: float = 0.0) -> torch.optim.Adam:
    """PyTorch's Adam on ``params``, fused into one kernel a step where they lie on a GPU
    (PyTorch's ``fused``; its default there launches about ten kernels per group a step)."""
    params = list(params)
    fused = bool(params) and all(p.is_cuda for p in params)
    return torch.optim.Adam(params, lr=lr, eps=eps, weight_decay=weight_decay, fused=fused or None)


def exponential_decay(lr_init: float, lr_final: float, max_steps: int):
    """The rate's multiplier at a step: from 1 to ``lr_final / lr_init`` exponentially over
    ``max_steps``, then constant (nerfstudio's ``ExponentialDecayScheduler`` without warm-up,
    to the same floats)."""

    def multiplier(step):
        t = np.clip(step / max_steps, 0, 1)
        return np.exp(np.log(lr_init) * (1 - t) + np.log(lr_final) * t) / lr_init

    return multiplier


class Optimisers:
    """One :func:`adam` per parameter group and the schedules of those that decay, in the
    interface nerfstudio's ``Optimizers`` has (``optimizers``, ``schedulers``, ``parameters``),
    which the fit's density control and stop read.

    Parameters
    ----------
    param_groups : name -> [Parameter], in the fit's order (:meth:`AtomFit.get_param_groups`)
    schedule_steps : the steps over which the decaying rates fall to their final values
    rates : name -> :class:`Rate` (default :data:`RATES`)
    """

    def __init__(
        self, param_groups: Dict[str, List[torch.nn.Parameter]], schedule_steps: int, rates: Dict[str, Rate] = RATES
    ) -> None:
        self.optimizers, self.schedulers, self.parameters = {}, {}, {}
        for name, params in param_groups.items():
            rate = rates[name]
            self.optimizers[name] = adam(params, rate.lr, rate.eps)
            self.parameters[name] = params
            if rate.lr_final is not None:
                self.schedulers[name] = lr_scheduler.LambdaLR(
                    self.optimizers[name], exponential_decay(rate.lr, rate.lr_final, schedule_steps)
                )

    def zero_grad_all(self) -> None:
        for optimizer in self.optimizers.values():
            optimizer.zero_grad()

    def step(self) -> None:
        """Adam's step for every group that has a gradient, then every schedule's."""
        for optimizer in self.optimizers.values():
            if any(any(p.grad is not None for p in g["params"]) for g in optimizer.param_groups):
                optimizer.step()
        for scheduler in self.schedulers.values():
            scheduler.step()

    def state_dict(self) -> dict:
        """The optimisers' and schedules' states, as nerfstudio's checkpoints hold them."""
        return {
            "optimizers": {k: v.state_dict() for k, v in self.optimizers.items()},
            "schedulers": {k: v.state_dict() for k, v in self.schedulers.items()},
        }
