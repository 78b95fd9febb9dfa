"""Iterate averaging: the Gaussians' estimate is the mean of the optimiser's last iterates,
not its last one.

With one view (or a few) per step the gradient is a sample, and Adam's iterates jitter about
the fit by more than the data's precision; only the learning-rate decay shrinks that jitter.
The mean of the iterates over a window (Polyak-Ruppert averaging) keeps the fit and cancels
the jitter, so the convergence check (:mod:`gaussian_atoms_method.engine.convergence`) stops
sooner with the same result.

A window is a run of steps over which the set of Gaussians stays the same (the parameter
tensors are the same objects: every duplicate, prune or merge replaces them,
:func:`.remap.apply_remap`); the trainer closes one at each refine, before the density control
acts, and at the end, and writes the mean into the parameters.  No nerfstudio import.
"""

from __future__ import annotations

from typing import Mapping

import torch

AVERAGED = ("means",)
"""The parameters averaged: the positions.  Not the masses and widths: those of noise Gaussians
fall for hundreds of steps until the prune takes them, and a mean lags such a trend (averaged
too, on Au noise 200 on the CPU, false atoms per atom at step 400 were 0.018 against 0.0096)."""


class IterateAverage:
    """The running mean of the averaged parameters since the window opened.

    Sums deviations from the window's first iterate, in the parameters' own dtype: the
    deviations are the jitter (a fraction of an Å), so float32 sums of a few hundred of them
    lose nothing the data can resolve."""

    def __init__(self, names: tuple[str, ...] = AVERAGED) -> None:
        self.names = names
        self.count = 0
        self._members: tuple = ()
        self._origin: dict[str, torch.Tensor] = {}
        self._sum: dict[str, torch.Tensor] = {}

    def _holds(self, params: Mapping[str, torch.Tensor]) -> bool:
        """Whether the open window holds iterates of ``params``' Gaussians (the same tensors)."""
        members = tuple(params[n] for n in self.names if n in params)
        return (
            self.count > 0
            and len(members) == len(self._members)
            and all(a is b for a, b in zip(members, self._members))
        )

    @torch.no_grad()
    def add(self, params: Mapping[str, torch.Tensor]) -> None:
        """Add the current iterate; opens a new window when the set of Gaussians changed."""
        if not self._holds(params):
            self._members, self.count = tuple(params[n] for n in self.names if n in params), 0
            self._origin = {n: params[n].detach().clone() for n in self.names if n in params}
            self._sum = {n: torch.zeros_like(v) for n, v in self._origin.items()}
        for n, total in self._sum.items():
            total += params[n].detach() - self._origin[n]
        self.count += 1

    def mean(self, params: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """name -> the window's mean where the window holds ``params``' Gaussians, else their
        current value (every parameter of ``params``, detached)."""
        out = {n: p.detach() for n, p in params.items()}
        if self._holds(params):
            out.update({n: self._origin[n] + self._sum[n] / self.count for n in self._sum})
        return out

    @torch.no_grad()
    def close(self, params: Mapping[str, torch.Tensor]) -> int:
        """Write the window's mean into ``params`` (when the window holds them) and open a new
        window; returns the iterates averaged (0: nothing written)."""
        count = self.count if self._holds(params) else 0
        if count > 1:
            for n, value in self.mean(params).items():
                if n in self._sum:
                    params[n].data.copy_(value)
        self.count, self._members, self._origin, self._sum = 0, (), {}, {}
        return count
