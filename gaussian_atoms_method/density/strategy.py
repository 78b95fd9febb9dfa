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
from typing import Callable, Mapping, MutableMapping

import numpy as np
import torch

from gaussian_atoms_method.atoms.merge import (
    cluster_labels,
    cluster_labels_on_device,
    disjoint_pair_labels,
    merged_values,
)
from gaussian_atoms_method.atoms.resolution import candidate_pairs, merge_energy, merged_moments
from gaussian_atoms_method.density.averaging import IterateAverage
from gaussian_atoms_method.density.remap import apply_remap, duplicate_remap, keep_remap, merge_remap
from gaussian_atoms_method.physics.data_terms import HUBER_EFFICIENCY
from gaussian_atoms_method.physics.projector import gaussian_mass, typical_mass

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


@dataclass
class DensityControl:
    """Duplicate, prune and merge Gaussians; see the module docstring for the rules.

    Attributes are the settings of :class:`~gaussian_atoms_method.nerfstudio_layer.options.GaussianAtomsOptions`
    of the same names (their docstrings say where each value comes from), with lengths converted
    by ``length_scale`` and ``max_log_amplitude`` (the amplitude ceiling of :meth:`clamp`) set by
    the model from the measured mass.
    """

    length_scale: float
    max_log_amplitude: float
    generator: torch.Generator
    min_sigma_A: float = 0.15
    max_sigma_A: float = 5.0
    max_atom_sigma_A: float = 1.5
    warmup_length: int = 200
    refine_every: int = 100
    stop_split_at: int = 2500
    densify_grad_thresh: float = 0.2
    max_gaussians: int = 200000
    prune_mass_fraction: float = 0.25
    false_alarm_rate: float = 0.05
    false_discovery_rate: float = 0.001
    add_from_residuals: bool = True
    split_heavy: bool = True
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
    cluster_merge: bool = True
    merge_every: int = 100
    merge_threshold_A: float = 0.7
    merge_amplitude: str = "mass"
    isotropic: bool = True
    average_iterates: bool = True
    """Write the mean of each refine interval's iterates into the parameters when it closes (before
    the refine acts) and at the end (:mod:`.averaging`)."""
    half_extent: tuple[float, float, float] = (0.5, 0.5, 0.5)
    """Half-sides of the reconstruction volume (normalised units): the cube the detector's longer
    side spans, or wider across the tilt axis for an object wider than the field of view
    (:mod:`..physics.field_of_view`)."""
    field_half_extent: tuple[float, float, float] | None = None
    """Half-sides of the field whose Gaussians are reported as atoms (normalised); None: the
    whole volume.  Beyond it (an object wider than the field of view) Gaussians only explain the
    rays that reach the detector through material outside the field; the final prune leaves
    them (a faint one there, pruned, would hand its signal to the atoms above the detector)."""
    grad_accum: torch.Tensor = field(default_factory=lambda: torch.zeros(0, 3))
    """(N, 3) sum of the means' gradient vectors since the last refine (CPU)."""
    grad_count: int = 0
    average: IterateAverage = field(default_factory=IterateAverage)
    """The iterates of the open refine interval (:mod:`.averaging`)."""
    born: torch.Tensor = field(default_factory=lambda: torch.zeros(0, dtype=torch.long))
    """(N,) step at which each Gaussian was made (0 for the start); fresh ones are not merged."""
    step: int = 0
    residual_clean: bool = False
    """A residual check found nothing to add: the later ones are skipped."""
    searched_at: int = 0
    """The step of the last residual search that added Gaussians (0: none yet)."""
    settled_since_search: bool = False
    """The final rules were applied mid-run since that search (:meth:`settle`)."""
    hard_core_A: float | None = None
    """The material's hard core from its species (Å, :func:`..atoms.hard_core.hard_core_from_species`);
    None: read from the confident atoms (:meth:`hard_core`)."""
    _hard_core_read: tuple = (0, math.inf)
    """The last reading from the atoms: (Gaussians then, hard core normalised)."""
    joined_close: int = 0
    """Gaussians joined into a partner closer than the hard core over the run (:meth:`join_close_pairs`)."""
    heavy_split: bool = False
    """The heavy Gaussians were split (:meth:`split_heavy_gaussians`: once a run)."""
    clamp_counts: torch.Tensor | None = None
    """(4,) Gaussian-steps held at the width floor, the width ceiling, the amplitude ceiling and
    the edge of the position box (kept on the parameters' device: no sync per step)."""
    pruned_outside: int = 0
    """Gaussians pruned for leaving the reconstruction volume ..."""
    pruned_outside_atom_like: int = 0
    """... of which heavy and narrow enough to be atoms (real atoms lost if centre_px is off)."""
    _boxes: dict = field(default_factory=dict, repr=False)
    """The position boxes as tensors, per device and dtype (:meth:`_box`)."""

    # ------------------------------------------------------------------ helpers
    @property
    def min_log_sigma(self) -> float:
        return math.log(self.min_sigma_A * self.length_scale)

    def _box(self, half_extent, like: torch.Tensor) -> torch.Tensor:
        """(3,) ``half_extent`` as a tensor on ``like``'s device and dtype, made once (a copy to
        the GPU at every step's clamp waited for it)."""
        key = (tuple(half_extent), like.device, like.dtype)
        if key not in self._boxes:
            self._boxes[key] = torch.as_tensor(half_extent, device=like.device, dtype=like.dtype)
        return self._boxes[key]

    def reset(self, n: int, device: torch.device | str | None = None) -> None:
        """Forget the accumulated gradients, for ``n`` Gaussians (kept on ``device``, default
        where they were: the parameters' device, so accumulating costs no copy to the host)."""
        self.grad_accum = torch.zeros(n, 3, device=self.grad_accum.device if device is None else device)
        self.grad_count = 0
        self._births(n)

    def _births(self, n: int) -> torch.Tensor:
        """The (n,) birth steps, started over at 0 (the start) when they are not for ``n``
        Gaussians (a strategy handed parameters it did not make)."""
        if self.born.shape[0] != n:
            self.born = torch.zeros(n, dtype=torch.long)
        return self.born

    def remap(
        self, params: Params, optimizers: Optimizers, src, dst, n_out: int, new_values=None, param_lists=None
    ) -> None:
        """Apply a remap (:mod:`.remap`) to the parameters, the optimisers' state, the
        accumulated gradients (merged Gaussians sum their pulls) and the birth steps (a merged
        Gaussian is as young as its youngest member)."""
        dev, n_in = params["means"].device, params["means"].shape[0]
        apply_remap(params, optimizers, src.to(dev), dst.to(dev), n_out, new_values, param_lists)
        at = self.grad_accum.device
        self.grad_accum = torch.zeros(n_out, 3, device=at).index_add_(0, dst.to(at), self.grad_accum[src.to(at)])
        src, dst = src.cpu(), dst.cpu()
        self.born = torch.zeros(n_out, dtype=torch.long).scatter_reduce_(
            0, dst, self._births(n_in)[src], reduce="amax", include_self=False
        )

    # ------------------------------------------------------------------ called by the training loop
    @torch.no_grad()
    def step_post_backward(self, params: Params, optimizers: Optimizers, step: int, param_lists=None) -> dict[str, int]:
        """After each optimiser step: clamp, accumulate the positional gradient and, every
        ``refine_every`` steps after the warm-up, duplicate and prune.  Returns the counts."""
        self.step = step
        self.clamp(params)
        if self.average_iterates:
            self.average.add(params)
            if step % self.refine_every == 0:  # the interval closes before the refine changes the set
                self.average.close(params)
        grad = params["means"].grad
        if grad is not None:
            if self.grad_accum.shape[0] != grad.shape[0] or self.grad_accum.device != grad.device:
                self.reset(grad.shape[0], grad.device)
            # Sum the gradient vectors, not their norms: with an L1 loss the per-step gradient of
            # a well-fitted Gaussian is noise that cancels, a persistent pull towards unexplained
            # signal does not.
            self.grad_accum += grad.detach()
            self.grad_count += 1
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
        self.step = step
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
            self.average.close(params)
        self.born = torch.zeros_like(self.born)  # at the end every Gaussian is judged
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

    def descendants(self, step: int) -> int:
        """How many Gaussians were made at ``step`` (or merged from one made then): what is left
        of the Gaussians a residual search added at ``step``."""
        return int((self.born == step).sum()) if step > 0 else 0

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
        if self.clamp_counts is None:
            self.clamp_counts = held
        else:
            self.clamp_counts.add_(held.to(self.clamp_counts.device))
        log_sigmas.clamp_(lo, hi)
        log_amps.clamp_(max=self.max_log_amplitude)
        means.clamp_(min=lower, max=bound)

    def report(self) -> list[str]:
        """What the safeguards did over the run, one sentence each (empty when nothing): the
        clamps of :meth:`clamp` and the prunes of Gaussians that left the volume."""
        lines = []
        if self.clamp_counts is not None:
            names = (
                f"widths held at the {self.min_sigma_A} Å floor",
                f"widths held at the {self.max_sigma_A} Å ceiling",
                "amplitudes held at the ceiling (1000x the measured mass)",
                "positions held at the edge of twice the volume",
            )
            held = [f"{int(n)} {name}" for n, name in zip(self.clamp_counts.tolist(), names) if n]
            if held:
                lines.append("clamped (Gaussian-steps): " + ", ".join(held))
        if self.pruned_outside:
            line = f"{self.pruned_outside} Gaussians left the reconstruction volume and were pruned"
            if self.pruned_outside_atom_like:
                line += (
                    f", {self.pruned_outside_atom_like} of them atom-like (check centre_px and pixel_size_A: atoms "
                    f"may lie outside the volume)"
                )
            lines.append(line)
        return lines

    @torch.no_grad()
    def densify(self, params: Params, optimizers: Optimizers, param_lists=None) -> int:
        """Duplicate Gaussians with a high mean positional gradient; each copy takes half the mass.
        Where the hard core is known (:meth:`hard_core`) the copy goes that far from its parent
        along the pull (against the mean gradient), the parent staying: a new atom is placed only
        where one can be, and a copy started half a width away could not leave the hard core
        within its interval before :meth:`join_close_pairs` took it back; otherwise the pair
        starts half a width apart in a random direction."""
        if self.grad_count == 0:
            return 0
        core = self.hard_core(params)
        n = params["means"].shape[0]
        mean_grad = (self.grad_accum / self.grad_count).norm(dim=-1)
        idx = torch.nonzero(mean_grad > self.densify_grad_thresh).flatten()
        room = self.max_gaussians - n
        if room <= 0 or len(idx) == 0:
            return 0
        idx = idx[
            torch.argsort(mean_grad[idx], descending=True)[:room]
        ].cpu()  # on the host, as the birth steps (the sums lie on the parameters' device)
        self.remap(params, optimizers, *duplicate_remap(n, idx), param_lists=param_lists)
        # Halve both amplitudes and move the pair apart by one sigma in a random direction.
        dev = params["means"].device
        both = torch.cat([idx, torch.arange(n, n + len(idx))]).to(dev)
        params["log_amplitudes"].data[both] -= math.log(2.0)
        if math.isfinite(core):
            pull = -self.grad_accum[:n].to(dev)[idx.to(dev)]
            params["means"].data[n:] += core * pull / pull.norm(dim=-1, keepdim=True).clamp_min(1e-30)
        else:
            direction = torch.randn(len(idx), 3, generator=self.generator).to(dev)
            direction = direction / direction.norm(dim=-1, keepdim=True)
            offset = 0.5 * direction * widths(params, self.min_log_sigma)[idx.to(dev), None]
            params["means"].data[idx.to(dev)] += offset
            params["means"].data[n:] -= offset
        self.born[idx] = self.step
        self.born[n:] = self.step
        return len(idx)

    @torch.no_grad()
    def add(
        self,
        params: Params,
        optimizers: Optimizers,
        means: torch.Tensor,
        sigma: float,
        masses: torch.Tensor,
        param_lists=None,
    ) -> int:
        """Append Gaussians at ``means`` (K, 3) of width ``sigma`` and integrated ``masses`` (K,)
        (normalised units), with fresh optimiser moments; at most up to ``max_gaussians``.
        Returns how many were added (they are fresh: not merged or pruned for one interval)."""
        n = params["means"].shape[0]
        means, masses = self.outside_hard_core(params, means, masses)
        self.residual_clean = len(means) == 0  # nothing found, or nothing where an atom can be
        k = min(len(means), self.max_gaussians - n)
        if k <= 0 or n == 0:
            return 0
        self.remap(params, optimizers, *duplicate_remap(n, torch.zeros(k, dtype=torch.long)), param_lists=param_lists)
        dev = params["means"].device
        params["means"].data[n:] = means[:k].to(params["means"])
        params["log_sigmas"].data[n:] = math.log(sigma)
        amps = masses[:k].double().clamp_min(1e-30) / (2.0 * math.pi * sigma**2) ** 1.5
        params["log_amplitudes"].data[n:, 0] = torch.log(amps).to(dev, params["log_amplitudes"].dtype)
        for name, param in params.items():
            state = optimizers[name].state.get(param, {}) if name in optimizers else {}
            for value in state.values():
                if torch.is_tensor(value) and value.dim() > 0 and value.shape[0] == n + k:
                    value[n:] = 0
        self.born[n:] = self.step
        return k

    def outside_hard_core(
        self, params: Params, means: torch.Tensor, masses: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The (K, 3) ``means`` and (K,) ``masses`` of new Gaussians less those within the hard
        core (:meth:`hard_core`) of an atom-like Gaussian inside the volume: no Gaussian is
        placed where no atom can be."""
        distance = self.hard_core(params)
        if len(means) == 0 or not math.isfinite(distance) or params["means"].shape[0] == 0:
            return means, masses
        from scipy.spatial import cKDTree

        atom_like = (self.atom_width(widths(params, self.min_log_sigma)) & self.inside(params["means"])).cpu().numpy()
        existing = params["means"].detach().double().cpu().numpy()[atom_like]
        if len(existing) == 0:
            return means, masses
        nearest, _ = cKDTree(existing).query(means.detach().double().cpu().numpy(), k=1)
        keep = torch.as_tensor(nearest >= distance)
        return means[keep.to(means.device)], masses[keep.to(masses.device)]

    @torch.no_grad()
    def split_heavy_gaussians(self, params: Params, optimizers: Optimizers, param_lists=None) -> int:
        """Split every settled atom-like Gaussian inside the volume that holds more than
        :data:`SPLIT_MASS` typical atoms' mass (:meth:`typical_atom_mass`) into two of half its
        mass, the material's shortest distance apart (:meth:`shortest_distance`) along the
        direction the views resolve worst (the beam directions' mean square: the missing wedge's
        axis), each of the typical atom's width; training then settles them, and the final stage
        merges back any pair the data prefer as one (:meth:`merge_by_likelihood`).  Once a run.

        Why: in a thick particle two atoms along the beam are told apart by the high tilts alone,
        and one Gaussian can settle on one of them holding both masses, with nothing left in the
        residual to say so.  On the 54,000-atom a-Pd particle (limited tilts) 94% of the 1,004
        missed atoms lay beside such a Gaussian: matched to a neighbour 1.75 Å away (median),
        mostly along the beam, holding a median 1.78 typical masses, 30% wider than the rest.
        Returns how many were split."""
        if self.heavy_split or not self.split_heavy or self.view_dirs is None or not self.isotropic:
            return 0
        self.heavy_split = True
        closest, _ = self.shortest_distance(params)
        if not math.isfinite(closest) or closest <= 0:
            return 0
        sig = widths(params, self.min_log_sigma).detach()
        mass = gaussian_mass(sig, amplitudes(params).detach())
        atom_like = self.atom_width(sig) & self.inside(params["means"])
        typical = self.typical_atom_mass(params)
        heavy = atom_like & (mass > SPLIT_MASS * typical) & ~self.fresh(len(mass)).to(mass.device)
        single = atom_like & ~heavy
        if typical <= 0 or not bool(heavy.any()) or not bool(single.any()):
            return 0
        u = self.view_dirs.detach().double().cpu()
        u = u / u.norm(dim=1, keepdim=True)
        _, vectors = torch.linalg.eigh(u.T @ u)
        axis = vectors[:, -1].to(params["means"])  # the direction the beams point along most
        idx = torch.nonzero(heavy).flatten().cpu()
        n = params["means"].shape[0]
        s_atom = float(sig[single].median())
        half_amp = 0.5 * mass[idx.to(mass.device)] / (2.0 * math.pi * s_atom**2) ** 1.5
        self.remap(params, optimizers, *duplicate_remap(n, idx), param_lists=param_lists)
        dev = params["means"].device
        both = torch.cat([idx, torch.arange(n, n + len(idx))]).to(dev)
        params["means"].data[idx.to(dev)] += 0.5 * closest * axis
        params["means"].data[n:] -= 0.5 * closest * axis
        params["log_sigmas"].data[both] = math.log(s_atom)
        params["log_amplitudes"].data[both, 0] = torch.log(torch.cat([half_amp, half_amp])).to(
            dev, params["log_amplitudes"].dtype
        )
        self.born[idx] = self.step
        self.born[n:] = self.step
        return len(idx)

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

    def in_field(self, means: torch.Tensor) -> torch.Tensor:
        """(N,) bool: inside the reported field (``field_half_extent``; the volume without one)."""
        if self.field_half_extent is None:
            return self.inside(means)
        return (means.abs() <= self._box(self.field_half_extent, means)).all(dim=-1)

    def inside(self, means: torch.Tensor) -> torch.Tensor:
        """(N,) bool: inside the reconstruction volume (``half_extent``, normalised units)."""
        return (means.abs() <= self._box(self.half_extent, means)).all(dim=-1)

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

    def residual_check_open(self, step: int) -> bool:
        """Whether the residuals are still to be searched for missing atoms (the model does it
        once the atoms are settled): ``add_from_residuals``, before ``stop_split_at`` (as
        duplication), and until a search finds nothing."""
        return self.add_from_residuals and not self.residual_clean and step < self.stop_split_at

    def fresh(self, n: int) -> torch.Tensor:
        """(n,) bool: made (duplicated or added) within the last ``refine_every`` steps."""
        born = self._births(n)
        return (born > 0) & (born > self.step - max(self.refine_every, self.merge_every))

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
        s = sigmas.double()  # normalised; 2D peak = mass / (2 pi s^2) in data units
        var = self.pixel_variance(mass, s)
        sd = torch.sqrt(self.efficiency * 8.0 * math.pi * var / max(self.n_views, 1)) * s * self.pixel_size
        return (mass / sd).to(sigmas.dtype)

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

    @torch.no_grad()
    def unresolved_pairs(
        self,
        params: Mapping[str, torch.Tensor],
        mergeable: torch.Tensor,
        weak: torch.Tensor | None = None,
        max_separation: float = math.inf,
    ) -> np.ndarray:
        """(K, 2) pairs of mergeable Gaussians the data cannot tell from one (:mod:`..atoms.resolution`):
        turning the pair into one Gaussian changes the projections by less chi-square (the
        pixels' noise variance from :meth:`pixel_variance` at the merged Gaussian, divided by
        the efficiency) than a noise-fitted pair gains, the chi-square quantile with 5 degrees
        of freedom (the pair's ten parameters against the merged one's five) at the family-wise
        rate of :meth:`significance_threshold`.  With ``weak`` (N,) bool, only pairs with a weak
        member; only pairs closer than ``max_separation`` (normalised).  Least resolved first;
        empty without a noise model or view directions."""
        if not self.noise_known() or self.view_dirs is None or int(mergeable.sum()) < 2:
            return np.zeros((0, 2), dtype=np.int64)
        from scipy.special import chdtri  # chi2.isf(p, df) is chdtri(df, p); scipy.stats' import is 0.3 s

        idx = torch.nonzero(mergeable.cpu()).flatten().numpy()
        sigmas = widths(params, self.min_log_sigma).detach().double().cpu().numpy()[idx]
        mass = gaussian_mass(torch.as_tensor(sigmas), amplitudes(params).detach().double().cpu()[idx]).numpy()
        pos = params["means"].detach().double().cpu().numpy()[idx]
        pairs = candidate_pairs(pos, sigmas)
        pairs = pairs[np.linalg.norm(pos[pairs[:, 0]] - pos[pairs[:, 1]], axis=1) < max_separation]
        if weak is not None:
            weak_idx = weak.cpu().numpy()[idx]
            pairs = pairs[weak_idx[pairs[:, 0]] | weak_idx[pairs[:, 1]]]
        if len(pairs) == 0:
            return pairs
        cost = merge_energy(pos, sigmas, mass, pairs, self.view_dirs.detach().double().cpu().numpy())
        _, s_c = merged_moments(pos, sigmas, mass, pairs)
        chi_square = cost / (self.pixel_size**2 * self.efficiency * self.pixel_variance(mass[pairs].sum(axis=1), s_c))
        level = chdtri(5, self.false_alarm_rate / self.cells())
        order = np.argsort(chi_square, kind="stable")
        return idx[pairs[order[chi_square[order] < level]]]

    @torch.no_grad()
    def likelihood_change(
        self, params: Mapping[str, torch.Tensor], pairs: np.ndarray, correlations
    ) -> np.ndarray | None:
        """(K,) for each pair of Gaussians ``(a, b)``: the data's chi-square with the pair made one
        Gaussian (at their mass-weighted centre and width, with their mass: the merge
        :meth:`_merge_labels` makes, by the same :func:`..atoms.merge.merged_values`) minus that with the pair.
        Negative: the data prefer one.

        With ``r`` the residual, ``p`` the pair's projections and ``s`` the merged one's, the
        change is ``sum w (p - s)^2 + 2 sum w r (p - s)`` (``w`` one over the noise variance): the
        first term is :func:`..atoms.resolution.merge_energy` over the noise at the merged
        Gaussian (:meth:`pixel_variance`), the second reads the residual through
        ``correlations`` (a callable of probe means (P, 3) and widths (P,) returning the (P,)
        sums ``sum w r g`` for unit-amplitude probes, :func:`..engine.residuals.residual_correlations`).
        None when it returns None or without a noise model or view directions."""
        if not self.noise_known() or self.view_dirs is None:
            return None
        pos = params["means"].detach().double()
        sig = widths(params, self.min_log_sigma).detach().double()
        amp = amplitudes(params).detach().double()
        pairs_t = torch.as_tensor(pairs, device=pos.device)
        members = pairs_t.flatten()  # each pair its own cluster of two
        centre, s_c, amp_c = merged_values(
            pos[members],
            sig[members],
            amp[members],
            torch.arange(len(pairs_t), device=pos.device).repeat_interleave(2),
            len(pairs_t),
            "mass",
        )
        unique = torch.unique(members)
        g = correlations(torch.cat([pos[unique], centre]), torch.cat([sig[unique], s_c]))
        if g is None:
            return None
        g_all = np.zeros(len(pos))
        g_all[unique.cpu().numpy()] = g[: len(unique)]
        pairs_np, a_np = np.asarray(pairs), amp.cpu().numpy()
        cross = (a_np[pairs_np] * g_all[pairs_np]).sum(axis=1) - amp_c.cpu().numpy() * g[len(unique) :]
        mass = gaussian_mass(sig, amp).cpu().numpy()
        energy = merge_energy(
            pos.cpu().numpy(),
            sig.cpu().numpy(),
            mass,
            pairs_np,
            self.view_dirs.detach().double().cpu().numpy(),
            merged=(centre.cpu().numpy(), s_c.cpu().numpy()),
        )
        chi_square = energy / (self.pixel_size**2 * self.pixel_variance(mass[pairs_np].sum(axis=1), s_c.cpu().numpy()))
        return chi_square + 2.0 * cross

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

        A family-wise level holds the chance of even one false atom in the whole volume at 5%,
        whatever the number of atoms; a 6,679-atom particle then pays in atoms: at Au noise 500,
        where an atom's mass stands 4.5-9 sigma high, the family-wise 5.1 dropped 3% of the
        atoms, the discovery level (4.2) kept them and added no false atom (0.9416 -> 0.9728
        TPR, 0.0247 -> 0.0250 false per atom, before the refit; the rate from 0.0005 to 0.005
        changed TPR by 0.002 and false atoms not at all: those left are fragments of atoms, not
        noise).  For a few hundred atoms it stays near the family-wise level (208 atoms in a
        25 Å box: 4.2 against 4.5)."""
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
        the measured mass among all candidates): the volume-wide threshold applied at step 200
        removed 206 of the 208 atoms of the aSi-208 counts at dose 8e3.  There a Gaussian goes
        when its mass is within one standard deviation of zero (:data:`TRAINING_SIGNIFICANCE`)
        or below ``prune_mass_fraction`` of a typical atom: the second is housekeeping that keeps
        noise candidates from holding mass while the atoms settle (with the first alone, the demo's
        RMSD went from 1.3 to 2.6 pm and the aSi-208 data at dose 1.6e5 kept 31 false atoms).  The
        final prune applies :meth:`discovery_threshold` alone."""
        sigmas = widths(params, self.min_log_sigma)
        noise_known = self.noise_known()
        keep = torch.ones_like(sigmas, dtype=torch.bool)
        if not (final and noise_known):  # the relative rule: without a noise model, or during training
            keep &= gaussian_mass(sigmas, amplitudes(params)) >= self.prune_mass_fraction * self.typical_atom_mass(
                params
            )
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
        self.pruned_outside += int((~inside).sum())
        self.pruned_outside_atom_like += int((keep & ~inside).sum())
        keep &= inside
        removed = int((~keep).sum())
        if removed:
            self.remap(params, optimizers, *keep_remap(keep.cpu()), param_lists=param_lists)
        return removed

    @torch.no_grad()
    def merge(self, params: Params, optimizers: Optimizers, param_lists=None, protect_fresh: bool = False) -> int:
        """Replace every cluster of Gaussians closer than merge_threshold_A by one; with
        ``protect_fresh``, Gaussians made in the last ``merge_every`` steps stay out."""
        means = params["means"]
        n = means.shape[0]
        mature = ~self.fresh(n) if protect_fresh else torch.ones(n, dtype=torch.bool)
        threshold = self.merge_threshold_A * self.length_scale
        if means.device.type == "cpu":
            labels, n_clusters = cluster_labels(means.detach().numpy(), threshold, mature.numpy())
        else:
            labels, n_clusters = cluster_labels_on_device(means, threshold, mature.to(means.device))
        return self._merge_labels(params, optimizers, labels, n_clusters, param_lists)

    @torch.no_grad()
    def merge_by_likelihood(
        self, params: Params, optimizers: Optimizers, param_lists=None, correlations=None, max_rounds: int = 4
    ) -> int:
        """Merge the pairs of atom-like Gaussians inside the volume whose merge raises the data's
        chi-square (:meth:`likelihood_change`, the residual read through ``correlations``) by
        less than two Gaussians gain by fitting noise: the chi-square quantile with 5 degrees of
        freedom at the family-wise rate of :meth:`unresolved_pairs`.  Pairwise, least change
        first, in rounds as :meth:`merge_unresolved` (each round reads the residual again).

        Why the residual: the resolution test (:meth:`unresolved_pairs`) asks whether the data
        *could* tell the pair from one Gaussian; a pair the data resolve may still fit them worse
        than one atom.  A least-squares fit at Au noise 500 shares 7% of the atoms between two
        Gaussians of nearly equal mass (median ratio 0.96) 1.1-1.8 Å apart along the missing
        wedge, both significant and resolved: 0.078 false atoms per atom.  Of 8,826 pairs there
        (all within :data:`..atoms.resolution.SEARCH_WIDTHS`), those of two atoms changed the
        chi-square by 62 or more in 99% (2 of 3,270 under the level of 39.8); merging every pair
        under the level took the false atoms from 0.203 to 0.040 per atom and the TPR from 0.9934
        to 0.9943, before the refit.

        A pair closer than the material's shortest distance (:meth:`shortest_distance`) stays two
        only where the likelihood demands it: its level is raised by the prior odds against a
        pair at its distance, the closer the more."""
        from scipy.special import chdtri  # chi2.isf(p, df) is chdtri(df, p); scipy.stats' import is 0.3 s

        level = chdtri(5, self.false_alarm_rate / self.cells())
        closest, prior = self.shortest_distance(params)

        def preferred_as_one(atom_like: torch.Tensor) -> np.ndarray:
            idx = torch.nonzero(atom_like).flatten().numpy()
            if len(idx) < 2:
                return np.zeros((0, 2), dtype=np.int64)
            pos = params["means"].detach().double().cpu().numpy()
            pairs = idx[
                candidate_pairs(pos[idx], widths(params, self.min_log_sigma).detach().double().cpu().numpy()[idx])
            ]
            change = self.likelihood_change(params, pairs, correlations) if len(pairs) else None
            if change is None:
                return np.zeros((0, 2), dtype=np.int64)
            distance = np.linalg.norm(pos[pairs[:, 0]] - pos[pairs[:, 1]], axis=1)
            margin = change - (level + np.where(distance < closest, prior(distance), 0.0))
            order = np.argsort(margin, kind="stable")
            return pairs[order[margin[order] < 0]]

        return self._merge_pairs_in_rounds(params, optimizers, param_lists, preferred_as_one, max_rounds)

    @torch.no_grad()
    def merge_unresolved(self, params: Params, optimizers: Optimizers, param_lists=None, max_rounds: int = 4) -> int:
        """Merge the pairs of atom-like Gaussians inside the volume that the data cannot resolve
        (:meth:`unresolved_pairs`), pairwise: in each round a greedy set of disjoint pairs, least
        resolved first (:func:`..atoms.merge.disjoint_pair_labels`), then the test again on the
        merged Gaussians.  Never by connected components: at Au noise 500 chains of unresolved
        links through the fragments between atoms merged whole neighbourhoods (TPR 0.61).
        ``max_rounds`` 4 rejoins an atom shared by up to 16 Gaussians.

        Two atoms are never closer than the material's shortest bond, read from the data
        (:meth:`shortest_bond`): a pair farther apart is left to the prune, whatever the test
        says.  At Au noise 500 a weak atom next to a neighbour 2.3-2.9 Å away can be as hard to
        resolve as an atom shared along the wedge (1.0-2.2 Å); without the bond the merge took
        2.5% of the atoms, with it TPR 0.9728 -> 0.9787 and false atoms 0.0250 -> 0.0222 per atom."""

        def unresolved(atom_like: torch.Tensor) -> np.ndarray:
            weak = (self.mass_significance(params) < self.significance_threshold()).cpu()
            return self.unresolved_pairs(
                params, atom_like, weak, self.shortest_bond(params["means"], ~weak & atom_like)
            )

        return self._merge_pairs_in_rounds(params, optimizers, param_lists, unresolved, max_rounds)

    def _merge_pairs_in_rounds(
        self, params: Params, optimizers: Optimizers, param_lists, ordered_pairs, max_rounds: int
    ) -> int:
        """Up to ``max_rounds`` rounds of: ``ordered_pairs`` of the (N,) CPU mask of atom-like
        Gaussians inside the volume gives (K, 2) pairs, best first; a greedy disjoint set of them
        is merged (:func:`..atoms.merge.disjoint_pair_labels`).  Stops when no pair is left;
        returns how many Gaussians went."""
        removed = 0
        for _ in range(max_rounds):
            atom_like = (self.atom_width(widths(params, self.min_log_sigma)) & self.inside(params["means"])).cpu()
            pairs = ordered_pairs(atom_like)
            if len(pairs) == 0:
                break
            removed += self._merge_labels(
                params, optimizers, *disjoint_pair_labels(params["means"].shape[0], pairs), param_lists
            )
        return removed

    def shortest_distance(self, params: Mapping[str, torch.Tensor]) -> tuple[float, Callable[[np.ndarray], np.ndarray]]:
        """The material's shortest interatomic distance (normalised), read from the pair
        distribution of the confident atoms (atom-like, in the field, significant at
        :meth:`significance_threshold`; :func:`..atoms.pair_distribution.first_shell`), and the
        chi-square a pair closer than that must gain over one Gaussian beyond the usual level, as
        a function of the (K,) pair distances: twice the log prior odds ``(1 - f) / f`` against
        it, with ``f`` the share of confident atoms with a neighbour that close
        (:meth:`..atoms.pair_distribution.FirstShell.share_closer`: a pair that is rare among the confident
        atoms needs that much more evidence).  (inf, no prior) with too few confident atoms or no
        noise model."""
        from gaussian_atoms_method.atoms.pair_distribution import first_shell

        def no_prior(distance: np.ndarray) -> np.ndarray:
            return np.zeros(np.shape(distance))

        if not self.noise_known():
            return math.inf, no_prior
        sigmas = widths(params, self.min_log_sigma)
        confident = (
            self.atom_width(sigmas)
            & self.in_field(params["means"])
            & (self.mass_significance(params) >= self.significance_threshold())
        )
        shell = first_shell(params["means"].detach()[confident].double().cpu().numpy())
        if not math.isfinite(shell.onset):
            return shell.onset, no_prior

        def prior(distance: np.ndarray) -> np.ndarray:
            f = shell.share_closer(distance)
            return np.maximum(2.0 * np.log(np.maximum(1.0 - f, 1e-300) / f), 0.0)

        return shell.onset, prior

    def hard_core(self, params: Mapping[str, torch.Tensor]) -> float:
        """The material's hard core, normalised: from its species (``hard_core_A``), else read from
        the confident atoms (atom-like, in the field, significant at :meth:`significance_threshold`;
        :func:`..atoms.hard_core.hard_core_from_positions`: their heavy ones' first shell), read
        again once the number of Gaussians has moved by a tenth since the last reading (a
        material's property: the 54,000-atom particles need not pay for it every interval).
        Infinite (nothing joined) without a noise model or with too few confident atoms."""
        if self.hard_core_A is not None:
            return self.hard_core_A * self.length_scale
        n = params["means"].shape[0]
        read_at, distance = self._hard_core_read
        if read_at and abs(n - read_at) <= 0.1 * read_at:
            return distance
        if not self.noise_known():
            return math.inf
        from gaussian_atoms_method.atoms.hard_core import hard_core_from_positions

        sigmas = widths(params, self.min_log_sigma)
        confident = (
            self.atom_width(sigmas)
            & self.in_field(params["means"])
            & (self.mass_significance(params) >= self.significance_threshold())
        ).cpu()
        mass = gaussian_mass(sigmas, amplitudes(params)).detach().double().cpu().numpy()
        distance, _ = hard_core_from_positions(
            params["means"].detach().double().cpu().numpy()[confident.numpy()],
            mass[confident.numpy()],
            self.typical_atom_mass(params),
        )
        self._hard_core_read = (n, distance) if math.isfinite(distance) else (0, math.inf)
        return distance

    @torch.no_grad()
    def join_close_pairs(
        self, params: Params, optimizers: Optimizers, param_lists=None, protect_fresh: bool = True
    ) -> int:
        """Join every pair of atom-like Gaussians inside the volume closer than the material's
        hard core (:meth:`hard_core`) into one at their mass-weighted centre, closest pairs first,
        in rounds (:meth:`_merge_pairs_in_rounds`); a pair holding more than :data:`SPLIT_MASS`
        typical atoms' mass is two atoms, moved apart to the hard core instead
        (:meth:`_push_apart`).  Training then settles them.
        Two atoms that close have zero prior probability whatever the likelihood gains: where the
        forward model misses something (a real film's probe, a denoiser's leftovers) the fit
        otherwise explains it with a second Gaussian 1.2-1.8 Å from the atom.  With
        ``protect_fresh`` the Gaussians made in the last interval stay out (a duplicate pair
        starts half a width apart).  Returns how many Gaussians went."""
        from gaussian_atoms_method.atoms.hard_core import close_pairs

        distance = self.hard_core(params)
        if not math.isfinite(distance) or params["means"].shape[0] < 2:
            return 0

        def too_close(atom_like: torch.Tensor) -> np.ndarray:
            mask = atom_like & ~self.fresh(len(atom_like)) if protect_fresh else atom_like
            idx = torch.nonzero(mask).flatten().numpy()
            pairs = idx[close_pairs(params["means"].detach().double().cpu().numpy()[idx], distance)]
            two = (
                self.atoms_worth(params).detach().cpu().numpy()[pairs].sum(axis=1) > SPLIT_MASS
                if len(pairs)
                else np.zeros(0, dtype=bool)
            )
            self._push_apart(params, pairs[two], distance)
            return pairs[~two]

        joined = self._merge_pairs_in_rounds(params, optimizers, param_lists, too_close, max_rounds=4)
        self.joined_close += joined
        return joined

    def _push_apart(self, params: Params, pairs: np.ndarray, distance: float) -> None:
        """Move each of the (K, 2) pairs apart along its axis to ``distance``, their centre of
        mass kept: a pair holding two atoms' mass (:data:`SPLIT_MASS`) is two atoms, too close."""
        if len(pairs) == 0:
            return
        # closest first; a Gaussian moves for one partner only
        labels, _ = disjoint_pair_labels(params["means"].shape[0], pairs)
        pairs = pairs[labels[pairs[:, 0]] == labels[pairs[:, 1]]]
        means = params["means"].data
        p = torch.as_tensor(pairs, device=means.device)
        mass = gaussian_mass(widths(params, self.min_log_sigma), amplitudes(params)).detach()
        a, b = means[p[:, 0]], means[p[:, 1]]
        axis = b - a
        gap = axis.norm(dim=-1, keepdim=True)
        axis = torch.where(
            gap > 0, axis / gap.clamp_min(1e-30), torch.tensor([0.0, 0.0, 1.0], device=means.device, dtype=means.dtype)
        )
        ma, mb = mass[p[:, 0], None], mass[p[:, 1], None]
        grow = (distance - gap).clamp_min(0.0)
        means[p[:, 0]] = a - axis * grow * mb / (ma + mb)
        means[p[:, 1]] = b + axis * grow * ma / (ma + mb)

    def shortest_bond(self, means: torch.Tensor, strong: torch.Tensor) -> float:
        """The 5th percentile of the nearest-neighbour distances among the ``strong`` (N,) bool
        Gaussians (normalised): the material's shortest bond as the data show it (Au 2.25 Å at
        noise 500; C-C 1.4 Å).  A low percentile, not the minimum: a few strong fragments of
        atoms sit closer.  Infinite with fewer than 20 strong Gaussians (too few to read it)."""
        pos = means.detach()[strong.to(means.device)].double().cpu().numpy()
        if len(pos) < 20:
            return math.inf
        from scipy.spatial import cKDTree

        distance, _ = cKDTree(pos).query(pos, k=2, workers=-1)
        return float(np.percentile(distance[:, 1], 5))

    def _merge_labels(
        self, params: Params, optimizers: Optimizers, labels: np.ndarray, n_clusters: int, param_lists=None
    ) -> int:
        """Replace each labelled cluster by one Gaussian (mass-weighted, :func:`..atoms.merge.merged_values`)."""
        means = params["means"]
        n = means.shape[0]
        if n_clusters == n:
            return 0
        labels_t = torch.as_tensor(labels, device=means.device)
        sigmas = widths(params, self.min_log_sigma)
        new_means, new_sigmas, amps = merged_values(
            means, sigmas, amplitudes(params), labels_t, n_clusters, self.merge_amplitude
        )
        new_values = {"means": new_means, "log_amplitudes": torch.log(amps)[:, None]}
        if self.isotropic:
            new_values["log_sigmas"] = torch.log(new_sigmas)[:, None]
        # Without isotropy the three log-widths (and rotations) take their cluster's mean.
        self.remap(params, optimizers, *merge_remap(labels_t.cpu(), n_clusters), new_values, param_lists)
        return n - n_clusters
