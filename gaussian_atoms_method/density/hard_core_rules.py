"""No two atoms closer than the material allows: the hard core (given or read from the
confident atoms, :mod:`gaussian_atoms_method.atoms.hard_core`), the join or push-apart of pairs
inside it, and additions kept outside it.  Mixed into
:class:`~gaussian_atoms_method.density.strategy.DensityControl`."""

from __future__ import annotations

import math
from typing import Callable, Mapping

import numpy as np
import torch

from gaussian_atoms_method.atoms.merge import (
    disjoint_pair_labels,
)
from gaussian_atoms_method.density.parameters import (
    SPLIT_MASS,
    Optimizers,
    Params,
    amplitudes,
    widths,
)
from gaussian_atoms_method.physics.projector import gaussian_mass


class HardCoreRules:
    """The hard-core rules of :class:`~gaussian_atoms_method.density.strategy.DensityControl`."""

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

    def known_hard_core(self) -> float:
        """The hard core as :meth:`hard_core` last had it, normalised, without reading it again
        (infinite before a reading): what an observer of the fit may ask without changing it."""
        if self.hard_core_A is not None:
            return self.hard_core_A * self.length_scale
        read_at, distance = self.state.hard_core_read
        return distance if read_at else math.inf

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
        read_at, distance = self.state.hard_core_read
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
        self.state.hard_core_read = (n, distance) if math.isfinite(distance) else (0, math.inf)
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
        self.state.joined_close += joined
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
