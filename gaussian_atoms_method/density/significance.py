"""Whether a Gaussian's mass stands above the measured noise: the noise model the prune judges
by, each Gaussian's mass significance, the training and final (false-discovery) levels, and the
prune.  Mixed into :class:`~gaussian_atoms_method.density.strategy.DensityControl`."""

from __future__ import annotations

import math
from typing import Mapping

import numpy as np
import torch

from gaussian_atoms_method.density.parameters import (
    TRAINING_SIGNIFICANCE,
    Optimizers,
    Params,
    amplitudes,
    widths,
)
from gaussian_atoms_method.density.remap import keep_remap
from gaussian_atoms_method.physics.data_terms import HUBER_EFFICIENCY
from gaussian_atoms_method.physics.projector import gaussian_mass, typical_mass


class Significance:
    """The noise judgement and prune of :class:`~gaussian_atoms_method.density.strategy.DensityControl`."""

    @torch.no_grad()
    def typical_atom_mass(self, params: Mapping[str, torch.Tensor]) -> float:
        """Mass-weighted median of the Gaussians' integrated masses: a typical atom's mass.

        Half of the total mass sits in Gaussians at least this heavy.  Faint leftovers may
        outnumber the atoms but carry little of the mass, so unlike a plain median this stays
        on the atoms.  Only atom-like widths (<= max_atom_sigma_A) count: on the aSi-208 data
        a Gaussian of 10 Å width grew to absorb the projections' constant background, held
        most of the mass, and the prune then removed every atom.
        """
        sigmas = widths(params, self.min_log_sigma)
        atom_like = self.atom_width(sigmas)
        return typical_mass(gaussian_mass(sigmas, amplitudes(params))[atom_like])

    def atoms_worth(self, params: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """(N,) each Gaussian's mass in typical atoms (:meth:`typical_atom_mass`)."""
        mass = gaussian_mass(widths(params, self.min_log_sigma), amplitudes(params))
        return mass / max(self.typical_atom_mass(params), 1e-300)

    def atom_width(self, sigmas: torch.Tensor) -> torch.Tensor:
        """(N,) bool: no wider than ``max_atom_sigma_A`` (the widest an atom can be)."""
        return sigmas <= self.max_atom_sigma_A * self.length_scale

    def set_noise(
        self,
        noise,
        floor: float,
        pixel_size: float,
        n_views: int,
        data_term: str,
        view_dirs: torch.Tensor | None = None,
    ) -> None:
        """The measured noise (normalised units) the prune judges masses against, the floor the
        atoms sit on, the pixel size (normalised), the number of views, the data term (L1
        estimates carry pi/2 the least-squares variance, Huber's 1/0.95) and the views' (V, 3) beam directions."""
        self.noise, self.floor, self.pixel_size, self.n_views, self.view_dirs = (
            noise,
            floor,
            pixel_size,
            n_views,
            view_dirs,
        )
        self.efficiency = {"l1": math.pi / 2, "huber": 1.0 / HUBER_EFFICIENCY}.get(data_term, 1.0)

    @torch.no_grad()
    def mass_significance(self, params: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """(N,) each Gaussian's mass over its Cramér-Rao standard deviation.

        A Gaussian of projected width ``s`` pixels and mass ``M``, fitted with its width over
        ``V`` views of pixel noise variance ``v``, has ``Var(M) = 8 pi s^2 v / V`` (pixel units;
        the amplitude alone would give ``4 pi s^2 v / V``: fitting the width doubles it), times
        the estimator's efficiency (pi/2 for L1).  ``v`` is the noise model's variance at the
        level the Gaussian's pixels sit on, weighted as the fit weights them: the floor plus
        2/3 of its projected peak (the g^2-weighted mean of a 2D Gaussian is 2/3 of its peak).
        A lower bound (neighbours' overlap only adds): atoms read more significant than they are,
        so it errs towards keeping.
        """
        sigmas = widths(params, self.min_log_sigma)
        mass = gaussian_mass(sigmas, amplitudes(params)).double()
        return self.significance_of(mass, sigmas.double()).to(sigmas.dtype)

    def significance_of(self, mass: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
        """(N,) :meth:`mass_significance` of Gaussians of ``mass`` and width ``s`` (normalised;
        2D peak = mass / (2 pi s^2) in data units), float64, under the noise model as it is now."""
        var = self.pixel_variance(mass, s)
        sd = torch.sqrt(self.efficiency * 8.0 * math.pi * var / max(self.n_views, 1)) * s * self.pixel_size
        return mass / sd

    def atom_like_leavers(self) -> int:
        """How many of the Gaussians above the field pruned for leaving the volume were atoms by
        the run's end: significant at :meth:`significance_threshold` under the noise it then
        judges in (the residual over an atom after the fit, where the run reads it), the level
        its confident atoms are read at.  Judged when they left, under the noise read before
        training and training's one standard deviation, noise Gaussians counted too: a real Ta
        sub-area read 12 lost atoms on correct geometry.  Without a noise model, all of them."""
        if not self.state.leavers:
            return 0
        if not self.noise_known():
            return sum(len(mass) for mass, _ in self.state.leavers)
        mass = torch.cat([m for m, _ in self.state.leavers])
        s = torch.cat([w for _, w in self.state.leavers])
        return int((self.significance_of(mass, s) >= self.significance_threshold()).sum())

    def pixel_variance(self, mass, s):
        """The noise variance (data units^2) of the pixels a Gaussian of ``mass`` and width ``s``
        (normalised) sits on, as the fit weights them: the noise model at the floor plus 2/3 of
        its projected peak ``mass / (2 pi s^2)`` (the g^2-weighted mean of a 2D Gaussian)."""
        level = self.floor + (2.0 / 3.0) * mass / (2.0 * math.pi * s**2)
        x = (level - self.noise.offset).clip(min=0.0)
        return (self.noise.read_var + self.noise.gain * x).clip(min=1e-300)

    def noise_known(self) -> bool:
        """Whether a noise model, pixel size and views are set (:meth:`set_noise`)."""
        return self.noise is not None and self.pixel_size > 0 and self.n_views > 0

    def significance_threshold(self) -> float:
        """The significance no noise blob should reach anywhere in the volume: the one-sided
        normal quantile at ``false_alarm_rate`` shared over the volume's cells of 1 Å^3 (no two
        atoms of any material are closer than about 1 Å, so there are no more independent
        places for an atom; the Gaussians sit where the noise is highest, so each cell is a
        trial).  A 25 Å box (the aSi-208 data): 15,600 cells, 4.5 sigma at 5%."""
        from statistics import NormalDist

        return NormalDist().inv_cdf(1.0 - self.false_alarm_rate / self.cells())

    def discovery_threshold(self, significance: torch.Tensor) -> float:
        """The final prune's level for these (N,) significances: the Benjamini-Hochberg level at
        ``false_discovery_rate`` over the volume's 1 Å^3 cells (the largest ``z`` with
        ``cells * P(Z > z) <= rate * #{significances >= z}``: the noise Gaussians expected above
        it are at most that fraction of those kept), never stricter than
        :meth:`significance_threshold`.

        A family-wise level holds the chance of even one false atom in the whole volume at
        ``false_alarm_rate``, whatever the number of atoms, so a large particle at high noise pays
        in weak atoms; the discovery level keeps them and adds no false atom.  For a few hundred
        atoms it stays near the family-wise level."""
        from scipy.special import ndtr  # the normal survival function: ndtr(-z), as scipy.stats computes it

        z = np.sort(significance.detach().double().cpu().numpy())[::-1]
        ok = np.nonzero(ndtr(-z) <= self.false_discovery_rate * np.arange(1, len(z) + 1) / self.cells())[0]
        return min(float(z[ok[-1]]) if len(ok) else math.inf, self.significance_threshold())

    def cells(self) -> float:
        """The reconstruction volume in Å^3: its number of 1 Å^3 cells (at least one)."""
        return max(math.prod(2.0 * h for h in self.half_extent) / self.length_scale**3, 1.0)

    @torch.no_grad()
    def prune(self, params: Params, optimizers: Optimizers, param_lists=None, final: bool = False) -> int:
        """Remove Gaussians whose mass is not significant (or, without a noise model, lighter
        than ``prune_mass_fraction`` of a typical atom), too wide to be an atom, or outside the
        reconstruction volume.

        During training (``final`` False) the masses are still being fitted (the start shares
        the measured mass among all candidates), and the volume-wide threshold would remove true
        atoms at low dose.  There a Gaussian goes when its mass is within one standard deviation
        of zero (:data:`TRAINING_SIGNIFICANCE`) or below ``prune_mass_fraction`` of a typical
        atom (times ``lightest_mass_ratio`` where lighter elements are given): the second is
        housekeeping that keeps noise candidates from holding mass while the atoms settle.  The
        final prune applies :meth:`discovery_threshold` alone."""
        sigmas = widths(params, self.min_log_sigma)
        noise_known = self.noise_known()
        keep = torch.ones_like(sigmas, dtype=torch.bool)
        if not (final and noise_known):  # the relative rule: without a noise model, or during training
            fraction = self.prune_mass_fraction * self.lightest_mass_ratio
            keep &= gaussian_mass(sigmas, amplitudes(params)) >= fraction * self.typical_atom_mass(params)
        if noise_known:
            # A fresh duplicate holds half its parent's mass: it has one refine interval to
            # gather what the data give it before it is judged.
            z = self.mass_significance(params)
            keep &= z >= (self.discovery_threshold(z) if final else TRAINING_SIGNIFICANCE)
            keep |= self.fresh(params["means"].shape[0]).to(sigmas.device)
            if final and self.field_half_extent is not None:
                keep |= ~self.in_field(params["means"])
        keep &= self.atom_width(sigmas)
        inside = self.inside(params["means"])
        self.state.pruned_outside += int((~inside).sum())
        leaving = (keep & ~inside & self.above_field(params["means"])).cpu()
        if leaving.any():
            mass = gaussian_mass(sigmas, amplitudes(params)).double().cpu()
            self.state.leavers.append((mass[leaving], sigmas.double().cpu()[leaving]))
        keep &= inside
        removed = int((~keep).sum())
        if removed:
            self.remap(params, optimizers, *keep_remap(keep.cpu()), param_lists=param_lists)
        return removed
