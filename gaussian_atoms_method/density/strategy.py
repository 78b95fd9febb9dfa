"""Density control: how many Gaussians there are, and where.

A strategy in the manner of gsplat's (``gsplat.strategy.DefaultStrategy``): an object that
holds its own state (the positional gradients accumulated over a refine interval, the random
generator of the duplications) and is called from the training loop after each backward pass.
It acts on the parameter dict (name -> ``nn.Parameter``: ``means`` (N, 3), ``log_sigmas``
(N, 1) or (N, 3), ``log_amplitudes`` (N, 1), optionally ``quats`` (N, 4)) and on the
optimisers' state through :mod:`.remap`, so Adam's moments follow their Gaussians.  Lengths
are in normalised units (``length_scale`` normalised units per Å, :mod:`..physics.units`).

The rules, every ``refine_every`` steps after ``warmup_length``:

* **duplicate** Gaussians whose mean positional gradient over the interval exceeds
  ``densify_grad_thresh`` (until ``stop_split_at``): each copy takes half the mass, the pair
  half a width apart;
* **prune** Gaussians whose mass is not significantly above zero given the measured noise
  (:meth:`DensityControl.mass_significance`: mass over its Cramér-Rao standard deviation below
  one during training; at the end below :meth:`DensityControl.discovery_threshold`, the level
  that keeps noise to ``false_discovery_rate`` of the atoms found), wider than ``max_atom_sigma_A`` or outside the
  reconstruction volume; without a
  noise model (a model built without data) lighter than ``prune_mass_fraction`` of a typical
  atom;
* **merge** (every ``merge_every`` steps, when ``cluster_merge``) clusters closer than
  ``merge_threshold_A`` into one Gaussian at their mass-weighted mean (the minimum-distance
  prior, :mod:`..atoms.merge`).  Gaussians made in the last ``merge_every`` steps (duplicates,
  additions) are not merged yet: a duplicate pair starts 1 sigma (about 0.6 Å) apart, inside
  the 0.7 Å threshold, and merging it at once undid every densification.

At the end (:meth:`DensityControl.finalize`): first every pair the data fit at least as well as
one Gaussian becomes one (:meth:`DensityControl.merge_by_likelihood`, the residual read through a
callable the model passes); then every pair of Gaussians the data cannot tell
from one (:meth:`DensityControl.unresolved_pairs`: merging them costs less chi-square than the
noise reaches, :mod:`..atoms.resolution`) becomes one, so an atom the fit shared between two
Gaussians along the missing wedge is judged whole; then the prune, so a noise blob the data do
resolve is not merged into an atom; then the distance merge; the model then refits briefly.

Every step the parameters are clamped to physical ranges (:meth:`DensityControl.clamp`) and
added to the refine interval's mean, which replaces them when the interval closes
(``average_iterates``, :mod:`.averaging`).
No nerfstudio import: unit-tested on plain parameter dicts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from gaussian_atoms_method.density.growth import Growth
from gaussian_atoms_method.density.hard_core_rules import HardCoreRules
from gaussian_atoms_method.density.merging import Merging
from gaussian_atoms_method.density.parameters import (
    Optimizers,
    Params,
    amplitudes,
    split_width,
    widths,
)
from gaussian_atoms_method.density.remap import apply_remap
from gaussian_atoms_method.density.settings import DensitySettings
from gaussian_atoms_method.density.significance import Significance
from gaussian_atoms_method.density.state import DensityState
from gaussian_atoms_method.physics.projector import gaussian_mass


@dataclass(kw_only=True)
class DensityControl(DensitySettings, Growth, Significance, Merging, HardCoreRules):
    """Duplicate, prune and merge Gaussians; see the module docstring for the rules.

    Its settings are :class:`~.settings.DensitySettings` (the fit's options of the same names),
    given by keyword; lengths are converted by ``length_scale``, and ``max_log_amplitude`` (the
    amplitude ceiling of :meth:`clamp`) is set by the model from the measured mass.
    """

    length_scale: float
    max_log_amplitude: float
    generator: torch.Generator
    noise: object | None = None
    """The pixel noise (:class:`~gaussian_atoms_method.physics.noise.NoiseModel`, normalised data
    units); None: unknown, the mass-fraction prune applies."""
    floor: float = 0.0
    """The background level the atoms sit on (normalised data units), for the Poisson part of the noise."""
    pixel_size: float = 0.0
    """Detector pixel size, normalised units."""
    n_views: int = 0
    view_dirs: torch.Tensor | None = None
    """(V, 3) the training views' beam directions, for the resolution test; None: not tested."""
    efficiency: float = 1.0
    """Variance of the fit's estimator over the least-squares one (pi/2 for L1)."""
    half_extent: tuple[float, float, float] = (0.5, 0.5, 0.5)
    """Half-sides of the reconstruction volume (normalised units): the cube the detector's longer
    side spans, or wider across the tilt axis for an object wider than the field of view
    (:mod:`..physics.field_of_view`)."""
    field_half_extent: tuple[float, float, float] | None = None
    """Half-sides of the field whose Gaussians are reported as atoms (normalised); None: the
    whole volume.  Beyond it (an object wider than the field of view) Gaussians only explain the
    rays that reach the detector through material outside the field; the final prune leaves
    them (a faint one there, pruned, would hand its signal to the atoms above the detector)."""
    hard_core_A: float | None = None
    """The material's hard core from its species (Å, :func:`..atoms.hard_core.hard_core_from_species`);
    None: read from the confident atoms (:meth:`hard_core`)."""
    lightest_mass_ratio: float = 1.0
    """The least mass an atom of the lightest element given can have against one of the heaviest
    (:func:`..atoms.species.lightest_mass_ratio`): the training prune's relative rule scales by it,
    so it never takes a light element's atoms for noise candidates.  1: one element, or none given."""
    state: DensityState = field(default_factory=DensityState)
    """What the rules keep between steps (:class:`.state.DensityState`)."""

    # ------------------------------------------------------------------ helpers
    @property
    def min_log_sigma(self) -> float:
        return math.log(self.min_sigma_A * self.length_scale)

    def _box(self, half_extent, like: torch.Tensor) -> torch.Tensor:
        """(3,) ``half_extent`` as a tensor on ``like``'s device and dtype, made once (a copy to
        the GPU at every step's clamp waited for it)."""
        key = (tuple(half_extent), like.device, like.dtype)
        if key not in self.state.boxes:
            self.state.boxes[key] = torch.as_tensor(half_extent, device=like.device, dtype=like.dtype)
        return self.state.boxes[key]

    def reset(self, n: int, device: torch.device | str | None = None) -> None:
        """Forget the accumulated gradients, for ``n`` Gaussians (kept on ``device``, default
        where they were: the parameters' device, so accumulating costs no copy to the host)."""
        self.state.grad_accum = torch.zeros(n, 3, device=self.state.grad_accum.device if device is None else device)
        self.state.grad_count = 0
        self._births(n)

    def _births(self, n: int) -> torch.Tensor:
        """The (n,) birth steps, started over at 0 (the start) when they are not for ``n``
        Gaussians (a strategy handed parameters it did not make)."""
        if self.state.born.shape[0] != n:
            self.state.born = torch.zeros(n, dtype=torch.long)
        if self.state.founded.shape[0] != n:
            self.state.founded = torch.zeros(n, dtype=torch.long)
        return self.state.born

    def remap(
        self, params: Params, optimizers: Optimizers, src, dst, n_out: int, new_values=None, param_lists=None
    ) -> None:
        """Apply a remap (:mod:`.remap`) to the parameters, the optimisers' state, the
        accumulated gradients (merged Gaussians sum their pulls) and the birth steps (a merged
        Gaussian is as young as its youngest member, and as old as its oldest:
        :attr:`~.state.DensityState.founded`)."""
        dev, n_in = params["means"].device, params["means"].shape[0]
        apply_remap(params, optimizers, src.to(dev), dst.to(dev), n_out, new_values, param_lists)
        at = self.state.grad_accum.device
        self.state.grad_accum = torch.zeros(n_out, 3, device=at).index_add_(
            0, dst.to(at), self.state.grad_accum[src.to(at)]
        )
        src, dst = src.cpu(), dst.cpu()
        self.state.born = torch.zeros(n_out, dtype=torch.long).scatter_reduce_(
            0, dst, self._births(n_in)[src], reduce="amax", include_self=False
        )
        self.state.founded = torch.zeros(n_out, dtype=torch.long).scatter_reduce_(
            0, dst, self.state.founded[src], reduce="amin", include_self=False
        )

    # ------------------------------------------------------------------ called by the training loop
    @torch.no_grad()
    def step_post_backward(self, params: Params, optimizers: Optimizers, step: int, param_lists=None) -> dict[str, int]:
        """After each optimiser step: clamp, accumulate the positional gradient and, every
        ``refine_every`` steps after the warm-up, duplicate and prune.  Returns the counts."""
        self.state.step = step
        self.clamp(params)
        if self.average_iterates:
            self.state.average.add(params)
            if step % self.refine_every == 0:  # the interval closes before the refine changes the set
                self.state.average.close(params)
        grad = params["means"].grad
        if grad is not None:
            if self.state.grad_accum.shape[0] != grad.shape[0] or self.state.grad_accum.device != grad.device:
                self.reset(grad.shape[0], grad.device)
            # Sum the gradient vectors, not their norms: with an L1 loss the per-step gradient of
            # a well-fitted Gaussian is noise that cancels, a persistent pull towards unexplained
            # signal does not.
            self.state.grad_accum += grad.detach()
            self.state.grad_count += 1
        if step < self.warmup_length or step % self.refine_every != 0:
            return {}
        # Pairs closer than the hard core are joined before the densify: a duplicate pair has had
        # its interval to move apart, and one that stayed inside the hard core is one atom.
        joined = self.join_close_pairs(params, optimizers, param_lists, protect_fresh=True)
        counts = {"joined": joined} if joined else {}
        counts["duplicated"] = self.densify(params, optimizers, param_lists) if step < self.stop_split_at else 0
        counts["pruned"] = self.prune(params, optimizers, param_lists)
        self.reset(params["means"].shape[0])
        return counts

    @torch.no_grad()
    def merge_step(self, params: Params, optimizers: Optimizers, step: int, param_lists=None) -> int:
        """Every ``merge_every`` steps after the warm-up (when ``cluster_merge``), merge."""
        self.state.step = step
        if self.cluster_merge and step >= self.warmup_length and step % self.merge_every == 0:
            return self.merge(params, optimizers, param_lists, protect_fresh=True)
        return 0

    @torch.no_grad()
    def finalize(self, params: Params, optimizers: Optimizers, param_lists=None, correlations=None) -> int:
        """Merge the pairs the data prefer as one (with ``correlations``, :meth:`merge_by_likelihood`),
        then those they cannot resolve, prune, then merge (fresh Gaussians too), so the result
        holds one Gaussian per atom; returns how many Gaussians went (the model refits when any
        did)."""
        if self.average_iterates:  # the last interval's mean: the estimate the final rules judge
            self.state.average.close(params)
        self.state.born = torch.zeros_like(self.state.born)  # at the end every Gaussian is judged
        return self.settle(params, optimizers, param_lists, correlations)

    @torch.no_grad()
    def settle(self, params: Params, optimizers: Optimizers, param_lists=None, correlations=None) -> int:
        """The final rules of :meth:`finalize` (merges by likelihood and resolution, the final
        prune, the distance merge) on the Gaussians as they stand; fresh ones keep their interval;
        the merge by likelihood only with ``correlations``.  Called mid-run, without them, once
        the positions have settled but the set has not (:func:`..engine.stopping.settle_set`).
        Returns how many Gaussians went."""
        removed = self.join_close_pairs(params, optimizers, param_lists, protect_fresh=True)
        if self.cluster_merge:
            removed += (
                self.merge_by_likelihood(params, optimizers, param_lists, correlations)
                if correlations is not None
                else 0
            )
            removed += self.merge_unresolved(params, optimizers, param_lists)
        removed += self.prune(params, optimizers, param_lists, final=True)
        if self.cluster_merge:
            removed += self.merge(params, optimizers, param_lists, protect_fresh=True)
        return removed

    @torch.no_grad()
    def additions_settled(self, params: Params) -> bool:
        """Whether the final rules' verdict on the Gaussians the last residual search added (and
        those merged from them) can wait no longer: False while any of them under the level no
        noise Gaussian reaches (:meth:`significance_threshold`) gained more than two of its
        standard deviations (its mass over its :meth:`mass_significance`: the 95% band of its
        estimate) since the previous call, matched by nearest position; so also at the first
        call after a search (nothing to compare yet).  A Gaussian added beside atoms that took up
        its mass gains it back only as they give it up; judged after one refine interval it was
        pruned or merged into a neighbour (on a 2,000-atom Ni-Pd-Pt particle through ADF
        physics, all three Ni atoms the last search found; all kept a second interval later).
        Called at each check; True without a search's additions or a noise model."""
        step = self.state.searched_at
        if not step or not self.noise_known():
            return True
        mask = (self.state.born == step).to(params["means"].device)
        mass = gaussian_mass(widths(params, self.min_log_sigma), amplitudes(params))[mask].double().cpu().numpy()
        z = self.mass_significance(params)[mask].double().cpu().numpy()
        sd = mass / z.clip(min=1e-12)
        pos = params["means"].detach()[mask].double().cpu().numpy()
        before, self.state.addition_masses = self.state.addition_masses, (step, pos, mass)
        if len(pos) == 0:
            return True
        if before is None or before[0] != step or len(before[1]) == 0:
            return False
        from scipy.spatial import cKDTree

        _, match = cKDTree(before[1]).query(pos)
        gaining = (mass - before[2][match] > 2.0 * sd) & (z < self.significance_threshold())
        return not gaining.any()

    def descendants(self, step: int) -> int:
        """How many Gaussians hold only what was made at ``step`` (or made from it since): what is
        left of the Gaussians a residual search added at ``step``.  An addition merged into a
        Gaussian from before the search found no atom of its own (:attr:`~.state.DensityState.founded`);
        counted by the youngest member, every addition that joined an atom survived (Au noise 200:
        187 of 187 two intervals after a search, against 0 of its own, and a second search ran).
        """
        return int((self.state.founded == step).sum()) if step > 0 else 0

    # ------------------------------------------------------------------ the rules
    @torch.no_grad()
    def clamp(self, params: Params) -> None:
        """Widths within [min_sigma_A, max_sigma_A]; amplitudes below ``max_log_amplitude``;
        positions within twice the volume.  Far outside what an atom can be, these bounds only
        stop a runaway Gaussian from overflowing float32."""
        ls = self.length_scale
        lo, hi = math.log(self.min_sigma_A * ls), math.log(self.max_sigma_A * ls)
        log_sigmas, log_amps, means = params["log_sigmas"].data, params["log_amplitudes"].data, params["means"].data
        twice = 2.0 * np.asarray(self.half_extent, dtype=np.float64)
        bound, lower = self._box(twice, means), self._box(-twice, means)  # made once each
        # A Gaussian counts once however many of its widths were held (one width when isotropic:
        # no reduction over it); the counts add in place (this runs every step).
        low, high = (
            (log_sigmas < lo, log_sigmas > hi)
            if log_sigmas.shape[-1] == 1
            else ((log_sigmas < lo).any(-1), (log_sigmas > hi).any(-1))
        )
        held = torch.stack(
            [low.sum(), high.sum(), (log_amps > self.max_log_amplitude).sum(), (means.abs() > bound).any(-1).sum()]
        )
        if self.state.clamp_counts is None:
            self.state.clamp_counts = held
        else:
            self.state.clamp_counts.add_(held.to(self.state.clamp_counts.device))
        log_sigmas.clamp_(lo, hi)
        log_amps.clamp_(max=self.max_log_amplitude)
        means.clamp_(min=lower, max=bound)

    def report(self) -> list[str]:
        """What the safeguards did over the run, one sentence each (empty when nothing): the
        clamps of :meth:`clamp` and the prunes of Gaussians that left the volume."""
        lines = []
        if self.state.clamp_counts is not None:
            names = (
                f"widths held at the {self.min_sigma_A} Å floor",
                f"widths held at the {self.max_sigma_A} Å ceiling",
                "amplitudes held at the ceiling (1000x the measured mass)",
                "positions held at the edge of twice the volume",
            )
            held = [f"{int(n)} {name}" for n, name in zip(self.state.clamp_counts.tolist(), names) if n]
            if held:
                lines.append("clamped (Gaussian-steps): " + ", ".join(held))
        if self.state.pruned_outside:
            line = f"{self.state.pruned_outside} Gaussians left the reconstruction volume and were pruned"
            atom_like = self.atom_like_leavers()
            if atom_like and self.field_half_extent is None:
                # the volume is the cube above the detector unless the run read a film: a film the
                # reading missed (a Ta replica fitted with extended_object off: 115 atom-like) is
                # named; a particle's geometry may be off
                line += (
                    f", {atom_like} of them atom-like (check centre_px and pixel_size_A; if the specimen is a film: "
                    f"extended_object on: atoms may lie outside the volume)"
                )
            elif atom_like:
                # a film: only those above the detector count (beyond it nothing is reported), and
                # they left through the faces along the beam, the cube's depth whatever the
                # geometry (the real Ta sub-area 23: 11, where the authors' model ends 7 Å inside)
                depth_A = self.half_extent[2] / self.length_scale
                line += (
                    f", {atom_like} of them atom-like above the detector: mass the views prove lies beyond the "
                    f"volume's depth along the beam ({depth_A:.0f} Å either side of the tilt axis): a support, a "
                    f"surface layer, or a film thicker than that"
                )
            lines.append(line)
        return lines

    def in_field(self, means: torch.Tensor) -> torch.Tensor:
        """(N,) bool: inside the reported field (``field_half_extent``; the volume without one)."""
        if self.field_half_extent is None:
            return self.inside(means)
        return (means.abs() <= self._box(self.field_half_extent, means)).all(dim=-1)

    def above_field(self, means: torch.Tensor) -> torch.Tensor:
        """(N,) bool: within the reported field across the beam (its first two axes), at any
        depth: a Gaussian there that leaves the volume leaves it along the beam, where the run
        would have reported it (the volume without a field)."""
        if self.field_half_extent is None:
            return torch.ones(means.shape[0], dtype=torch.bool, device=means.device)
        return (means[:, :2].abs() <= self._box(self.field_half_extent, means)[:2]).all(dim=-1)

    def counted_worth(self, params) -> torch.Tensor:
        """(N,) each Gaussian's mass in typical atoms (:meth:`atoms_worth`), zero beyond the
        reported field (:meth:`in_field`) and for a Gaussian wider than one atom is imaged
        (:func:`.parameters.split_width` of the atom-like widths): the atoms whose set a run
        must settle before it stops.  Beyond the field a film's material is seen only in the
        tilted views, and its Gaussians come and go with them.  A Gaussian wider than an atom
        holds material no atom explains (a support, a surface layer) or two atoms the heavy
        split will part; on a real Ta sub-area (23, on a GPU) such Gaussians took up 1-7 atoms'
        mass each at the film's surfaces, widened to the widest an atom can be and were pruned,
        one to four each 100 steps until the step limit."""
        return self.field_worths(params)[0]

    def field_worths(self, params) -> tuple[torch.Tensor, torch.Tensor]:
        """(N,) :meth:`counted_worth`, and (N,) the worth of each Gaussian of one atom's width
        beyond the reported field (zero in it): what a merge across the field's edge carries in."""
        sig = widths(params, self.min_log_sigma).detach()
        one_atom = self.atoms_worth(params) * (sig <= split_width(sig[self.atom_width(sig)]))
        in_field = self.in_field(params["means"].detach())
        return one_atom * in_field, one_atom * ~in_field

    def inside(self, means: torch.Tensor) -> torch.Tensor:
        """(N,) bool: inside the reconstruction volume (``half_extent``, normalised units)."""
        return (means.abs() <= self._box(self.half_extent, means)).all(dim=-1)

    def residual_check_open(self, step: int) -> bool:
        """Whether the residuals are still to be searched for missing atoms (the model does it
        once the atoms are settled): ``add_from_residuals``, before ``stop_split_at`` (as
        duplication), and until a search finds nothing."""
        return self.add_from_residuals and not self.state.residual_clean and step < self.stop_split_at

    def fresh(self, n: int) -> torch.Tensor:
        """(n,) bool: made (duplicated or added) within the last ``refine_every`` steps."""
        born = self._births(n)
        return (born > 0) & (born > self.state.step - max(self.refine_every, self.merge_every))
