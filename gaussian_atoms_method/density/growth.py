"""Where Gaussians are added: duplicates of those the data pull hardest on, additions at sites the
residual shows, and the split of a Gaussian holding two atoms' mass.  Mixed into
:class:`~gaussian_atoms_method.density.strategy.DensityControl`, whose fields they read."""

from __future__ import annotations

import math

import torch

from gaussian_atoms_method.density.parameters import (
    Optimizers,
    Params,
    amplitudes,
    split_width,
    split_worth,
    widths,
)
from gaussian_atoms_method.density.remap import duplicate_remap
from gaussian_atoms_method.physics.projector import gaussian_mass


class Growth:
    """The growth rules of :class:`~gaussian_atoms_method.density.strategy.DensityControl`."""

    @torch.no_grad()
    def densify(self, params: Params, optimizers: Optimizers, param_lists=None) -> int:
        """Duplicate Gaussians with a high mean positional gradient; each copy takes half the mass.
        Where the hard core is known (:meth:`hard_core`) the copy goes that far from its parent
        along the pull (against the mean gradient), the parent staying: a new atom is placed only
        where one can be, and a copy started half a width away could not leave the hard core
        within its interval before :meth:`join_close_pairs` took it back; otherwise the pair
        starts half a width apart in a random direction."""
        if self.state.grad_count == 0:
            return 0
        core = self.hard_core(params)
        n = params["means"].shape[0]
        mean_grad = (self.state.grad_accum / self.state.grad_count).norm(dim=-1)
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
            pull = -self.state.grad_accum[:n].to(dev)[idx.to(dev)]
            params["means"].data[n:] += core * pull / pull.norm(dim=-1, keepdim=True).clamp_min(1e-30)
        else:
            direction = torch.randn(len(idx), 3, generator=self.generator).to(dev)
            direction = direction / direction.norm(dim=-1, keepdim=True)
            offset = 0.5 * direction * widths(params, self.min_log_sigma)[idx.to(dev), None]
            params["means"].data[idx.to(dev)] += offset
            params["means"].data[n:] -= offset
        self.state.born[idx] = self.state.step
        self._made_now(n)
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
        self.state.residual_clean = len(means) == 0  # nothing found, or nothing where an atom can be
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
        self._made_now(n)
        return k

    @torch.no_grad()
    def split_heavy_gaussians(self, params: Params, optimizers: Optimizers, param_lists=None) -> int:
        """Split every settled atom-like Gaussian inside the volume heavier than a single atom can
        be (:func:`.parameters.split_worth`, in typical atoms' mass: :meth:`typical_atom_mass`)
        into two of half its mass, the material's shortest distance apart (:meth:`shortest_distance`) along the
        direction the views resolve worst (the beam directions' mean square: the missing wedge's
        axis), each of the typical atom's width; training then settles them, and the final stage
        merges back any pair the data prefer as one (:meth:`merge_by_likelihood`).  Once a run.

        Why: in a thick particle two atoms along the beam are told apart by the high tilts alone,
        and one Gaussian can settle on one of them holding both masses, with nothing left in the
        residual to say so.  On the 54,000-atom a-Pd particle (limited tilts) 94% of the 1,004
        missed atoms lay beside such a Gaussian: matched to a neighbour 1.75 Å away (median),
        mostly along the beam, holding a median 1.78 typical masses, 30% wider than the rest.
        Returns how many were split."""
        if self.state.heavy_split or not self.split_heavy or self.view_dirs is None or not self.isotropic:
            return 0
        self.state.heavy_split = True
        closest, _ = self.shortest_distance(params)
        if not math.isfinite(closest) or closest <= 0:
            return 0
        sig = widths(params, self.min_log_sigma).detach()
        mass = gaussian_mass(sig, amplitudes(params).detach())
        atom_like = self.atom_width(sig) & self.inside(params["means"])
        typical = self.typical_atom_mass(params)
        worth = mass / max(typical, 1e-300)
        two = (worth > split_worth(worth[atom_like])) | (sig > split_width(sig[atom_like]))
        heavy = atom_like & two & ~self.fresh(len(mass)).to(mass.device)
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
        self.state.born[idx] = self.state.step
        self._made_now(n)
        return len(idx)

    def _made_now(self, first: int) -> None:
        """The Gaussians from index ``first`` on were made at this step: born now, and founded
        now (a copy or an addition holds none of the Gaussians before it)."""
        self.state.born[first:] = self.state.step
        self.state.founded[first:] = self.state.step
