"""Which Gaussians become one: pairs the data fit as well as one (likelihood), pairs the data
cannot tell from one (resolution), and clusters closer than the merge distance.  Mixed into
:class:`~gaussian_atoms_method.density.strategy.DensityControl`."""

from __future__ import annotations

import math
from typing import Mapping

import numpy as np
import torch

from gaussian_atoms_method.atoms.merge import (
    cluster_labels,
    cluster_labels_on_device,
    disjoint_pair_labels,
    merged_values,
)
from gaussian_atoms_method.atoms.resolution import candidate_pairs, merge_energy, merged_moments
from gaussian_atoms_method.density.parameters import (
    SPLIT_MASS,
    Optimizers,
    Params,
    amplitudes,
    widths,
)
from gaussian_atoms_method.density.remap import merge_remap
from gaussian_atoms_method.physics.projector import gaussian_mass


class Merging:
    """The merge rules of :class:`~gaussian_atoms_method.density.strategy.DensityControl`."""

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
        than one atom: at high noise a least-squares fit shares some atoms between two Gaussians
        of nearly equal mass a bond's fraction apart along the missing wedge, both significant
        and resolved, while a pair of two atoms changes the chi-square far more than the level.

        A pair closer than the material's shortest distance (:meth:`shortest_distance`) stays two
        only where the likelihood demands it: its level is raised by the prior odds against a
        pair at its distance, the closer the more.

        A pair that is one peak (closer than the sum of its widths: two Gaussians that close sum
        to a single maximum) and holds no more than :data:`..parameters.SPLIT_MASS` typical
        atoms' mass (halfway between one and two) is one atom whatever the likelihood says: two
        atoms would hold two atoms' mass, and the likelihood's preference is one atom's shape
        that the forward model misses (through an aberrated probe, a pair along the beam around
        one true atom).  Not the material's shortest distance in its place: that merged pairs
        the split had made of two true atoms just under its onset.

        A pair holding more than :data:`..parameters.SPLIT_MASS` typical atoms' mass is two atoms
        whatever the likelihood says, as :meth:`join_close_pairs` keeps it: an atom shared
        between two Gaussians leaves them one atom's mass, and a Gaussian of two atoms' mass is
        one the split proposes again.  Through a probe the fit does not share, two carbon atoms a
        bond apart fit one Gaussian within the level at a low dose (ptychographic phase images at
        2,000 e/Å²: 255 of 1,512 atoms merged away, 0.82 found; kept, 0.97)."""
        from scipy.special import chdtri  # chi2.isf(p, df) is chdtri(df, p); scipy.stats' import is 0.3 s

        level = chdtri(5, self.false_alarm_rate / self.cells())
        closest, prior = self.shortest_distance(params)

        def preferred_as_one(atom_like: torch.Tensor) -> np.ndarray:
            idx = torch.nonzero(atom_like).flatten().numpy()
            if len(idx) < 2:
                return np.zeros((0, 2), dtype=np.int64)
            pos = params["means"].detach().double().cpu().numpy()
            sigmas = widths(params, self.min_log_sigma).detach().double().cpu().numpy()
            pairs = idx[candidate_pairs(pos[idx], sigmas[idx])]
            change = self.likelihood_change(params, pairs, correlations) if len(pairs) else None
            if change is None:
                return np.zeros((0, 2), dtype=np.int64)
            distance = np.linalg.norm(pos[pairs[:, 0]] - pos[pairs[:, 1]], axis=1)
            margin = change - (level + np.where(distance < closest, prior(distance), 0.0))
            # one atom's mass in one peak: one atom, whatever its shape's misfit
            worth = self.atoms_worth(params).detach().double().cpu().numpy()[pairs].sum(axis=1)
            margin[(distance < sigmas[pairs].sum(axis=1)) & (worth <= SPLIT_MASS)] = -np.inf
            margin[worth > SPLIT_MASS] = np.inf  # two atoms' mass: two atoms, as join_close_pairs
            order = np.lexsort((distance, margin))
            return pairs[order[margin[order] < 0]]

        return self._merge_pairs_in_rounds(params, optimizers, param_lists, preferred_as_one, max_rounds)

    @torch.no_grad()
    def merge_unresolved(self, params: Params, optimizers: Optimizers, param_lists=None, max_rounds: int = 4) -> int:
        """Merge the pairs of atom-like Gaussians inside the volume that the data cannot resolve
        (:meth:`unresolved_pairs`), pairwise: in each round a greedy set of disjoint pairs, least
        resolved first (:func:`..atoms.merge.disjoint_pair_labels`), then the test again on the
        merged Gaussians.  Never by connected components: at high noise chains of unresolved
        links through the fragments between atoms merge whole neighbourhoods.
        ``max_rounds`` 4 rejoins an atom shared by up to 16 Gaussians.

        Two atoms are never closer than the material's shortest bond, read from the data
        (:meth:`shortest_bond`): a pair farther apart is left to the prune, whatever the test
        says: at high noise a weak atom a bond from its neighbour can be as hard to resolve as an
        atom shared along the wedge."""

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
