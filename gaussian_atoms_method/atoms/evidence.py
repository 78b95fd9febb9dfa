"""Each atom with its evidence: what the views lose without it, how far its depth is open, and
its position precision with its neighbours re-fitted.

The views are the projections of isotropic Gaussians: in a view with detector axes ``P_v``
(2 x 3) an atom (position ``r``, width ``sigma``, 3D peak ``q``) is the 2D Gaussian
``g(u) = q sigma sqrt(2 pi) exp(-|u - P_v r|^2 / (2 sigma^2))``.  Under pixel noise of standard
deviation ``s`` (pixel side ``p``) the curvature of the least-squares cost about the fit, the
Fisher information, couples every pair of parameters through the overlap of their derivatives::

    F_ab = 1 / (s^2 p^2) sum_v integral (dg/da)(dg/db) du

and for two Gaussians the integral is closed: their product is a Gaussian (centre ``m``,
variance ``tau^2`` per axis), and each derivative is a polynomial in ``u - m`` whose moments
under it are known (:func:`.information.pair_information`).  From ``F`` restricted to an atom and its
neighbours (the atoms whose information about each other is not negligible,
:data:`COUPLING_FLOOR`):

* **existence**: the cost the views gain when the atom is taken out and its neighbours re-fitted,
  ``q^2 / [M^-1]_qq`` with ``M`` the information of the atom's amplitude and every parameter of
  its neighbours (the Schur complement: the neighbours take up what they can of its image).  Its
  square root is a significance in units of the noise: the views' misfit without the atom, in
  standard deviations of the residual at the atom's scale (its level times its spectrum's weight
  for an atom's template, :func:`.information.residual_spectrum_factors`: what a blob of residual structure
  the size of an atom reaches by chance).  An atom is **proven** where it exceeds the level a pure-noise site would
  reach by chance among as many sites as atoms reported (:func:`proof_level`), else **open**;
* **depth**: the covariance of the atom's position with every neighbour re-fitted is the
  quadratic profile of the cost; its widest axis is the direction the views fix least (the beam,
  for a missing wedge).  The 95% interval along it is the depth interval, **open in depth** where
  it is wider than half the hard core (two atoms could trade places along it);
* **precision**: the same covariance's diagonal, ``std_x/y/z`` (the isolated atom's Cramér-Rao
  bound, :mod:`.uncertainty`, is its lower bound: neighbours only widen it).

The noise is the residual that is there, not the noise the views were measured to hold: with
each view's pull on each atom (:func:`view_scores`, the residual correlated with the atom's
derivatives), the covariance is the sandwich ``F^-1 (sum_v g_v g_v^T) F^-1`` with the views as
independent clusters, which holds whatever the residual's structure within a view
(misregistration, a support's texture, a misfit the model cannot explain).  Without the pulls,
white noise of the residual's level weighted by its spectrum at the atoms' scale.
On a replica of a Ta film sub-area (misregistration, a carbon support, an aberrated probe) the
white-noise intervals held 0.64-0.70 of the actual errors, the sandwich's 0.90-0.93.  What no
view-by-view spread can see, a bias the same in every view, stays outside both.  All in the
continuum limit (pixel sums as integrals: exact to far below a percent for a Gaussian wider than
a pixel); given the detector's extent, each view counts by the share of a pair it holds.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from gaussian_atoms_method.atoms.calibration import Z95, precision_floor_A, wider_than_half_core
from gaussian_atoms_method.atoms.depth_profile import depth_axis_of, depth_rises, moved_blocks_of
from gaussian_atoms_method.atoms.information import (
    BATCH_ELEMENTS,
    DEVICE_PAIR_VIEWS,
    HOST_BATCH_ELEMENTS,
    amplitude_coupling,
    local_information,
    local_sets,
    pair_information,
    pairs_among_neighbours,
)
from gaussian_atoms_method.atoms.population import with_prior
from gaussian_atoms_method.physics.devices import work_device
from gaussian_atoms_method.physics.spd import spd_inverse, spd_inverse_rows, spd_solve

COUPLING_FLOOR = 0.02
"""Neighbours are the atoms whose amplitudes' information correlation with the atom,
``|F_qiqj| / sqrt(F_qiqi F_qjqj)``, reaches this.  A coupling ``rho`` changes a marginal variance by
about ``rho^2`` of itself: one left out changes a variance by well under a percent."""

NEIGHBOUR_SEARCH_A = 6.0
"""The pairs whose coupling is computed lie within this many Å of each other.  Beyond it two
atoms' images meet only in the views in which one lies nearly behind the other along the beam,
each such coupling weak; they are many (on a Ta sub-area's 1,880 Gaussians, 2,307 pairs within
3 Å reach :data:`COUPLING_FLOOR`, 10,555 within 6 Å) and left out: the replicas' coverage of the
stated intervals (docs/evidence.md) is the check that they may be."""

FAMILY_FALSE_ALARM = 0.05
"""The chance that any one of the reported atoms would be called proven were its site pure
noise (the family-wise error of :func:`proof_level`)."""


def proof_level(n_atoms: int, family_false_alarm: float = FAMILY_FALSE_ALARM) -> float:
    """The significance (noise standard deviations) above which an atom is called proven: the
    one-sided normal quantile at ``family_false_alarm / n_atoms`` (Bonferroni over the atoms
    reported), so that among ``n_atoms`` sites of pure noise none would pass with probability
    ``1 - family_false_alarm``.

    >>> round(proof_level(1000), 2)
    3.89
    """
    from scipy.special import ndtri

    return float(-ndtri(family_false_alarm / max(int(n_atoms), 1)))


@dataclass
class AtomEvidence:
    """Per atom: ``significance`` (N,), the views' misfit without it, neighbours re-fitted,
    in noise standard deviations; ``proven`` (N,) bool, significance at or above ``proof_level``;
    ``position_std_A`` (N, 3), its precision along x, y, z with its neighbours re-fitted;
    ``depth_halfwidth_A`` (N,), the 95% half-width along ``depth_axis`` (N, 3), the direction
    the views fix least; ``depth_open`` (N,) bool, that interval wider than half the hard core, or
    another place along the axis as good or better; ``depth_profile`` (N, M), the cost's rise in noise
    variances with the atom moved by each of ``depth_offsets_A`` (M,) along the depth axis, the
    rest re-fitted (empty without the moved pulls); ``width_std_A`` (N,), the precision of its
    width, found the same way as its position's; ``depth_scatter`` (N,), the stated variance
    along the depth axis over the one the noise alone gives (at least 1: the residual the atom's
    own views show, :func:`atom_evidence`)."""

    significance: np.ndarray
    proven: np.ndarray
    position_std_A: np.ndarray
    depth_halfwidth_A: np.ndarray
    depth_axis: np.ndarray
    depth_open: np.ndarray
    proof_level: float
    hard_core_A: float | None
    depth_offsets_A: np.ndarray = field(default_factory=lambda: np.zeros(0))
    depth_profile: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    width_std_A: np.ndarray = field(default_factory=lambda: np.zeros(0))
    depth_scatter: np.ndarray = field(default_factory=lambda: np.zeros(0))
    log_mass_std: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """(N,) the standard deviation of the atom's log mass (its relative precision), its
    neighbours and its own other parameters re-fitted, from the residual its views show."""

    @property
    def depth_rise(self) -> np.ndarray:
        """(N,) the profile's least rise over the places it tried, in the atom's stated variance
        along the depth axis (the noise's times ``depth_scatter``): how much worse the best other
        place fits; under ``Z95^2`` it lies within the 95% interval (NaN where none is known)."""
        profile = self.depth_profile
        if profile.size == 0:
            return np.full(len(self.significance), np.nan)
        known = np.isfinite(profile)
        least = np.where(known.any(axis=1), np.min(np.where(known, profile, np.inf), axis=1), np.nan)
        return least / (self.depth_scatter if len(self.depth_scatter) else 1.0)


def _pairs(positions: np.ndarray, radius_A: float) -> np.ndarray:
    from scipy.spatial import cKDTree

    if len(positions) < 2:
        return np.zeros((0, 2), dtype=np.int64)
    return cKDTree(positions).query_pairs(radius_A, output_type="ndarray").astype(np.int64)


def atom_evidence(
    positions_A: np.ndarray,
    sigmas_A: np.ndarray,
    amplitudes: np.ndarray,
    detector_axes: np.ndarray,
    pixel_size_A: float,
    noise_std: float,
    hard_core_A: float | None = None,
    loss: str = "l2",
    position_factor: float = 1.0,
    amplitude_factor: float = 1.0,
    scores: np.ndarray | None = None,
    targets: np.ndarray | None = None,
    chunk_pairs: int = 4096,
    moved_pulls: dict | None = None,
    device=None,
    progress=None,
    field=None,
    population=None,
) -> AtomEvidence:
    """Existence, depth and precision of every atom from the views' information (module docstring).

    Parameters
    ----------
    positions_A : (N, 3) array
    sigmas_A, amplitudes : (N,) arrays
        Widths (Å) and 3D peaks (projection units per Å), as :class:`~.atom_set.AtomSet` holds them.
    detector_axes : (V, 2, 3) or (V, 3, 3) array
    pixel_size_A : float
    noise_std : float
        The residual's pixel standard deviation, projection units.
    hard_core_A : float, optional
        The shortest distance two atoms keep; without it no atom is called open in depth.
    loss : {"l1", "l2"}
        The data term the positions were fitted with: an L1 fit's variance is ``pi / 2`` times
        the least-squares one under Gaussian noise (:data:`.uncertainty.L1_EFFICIENCY_FACTOR`).
    position_factor, amplitude_factor : float
        The residual spectrum's weight at the atoms' scale against white noise of ``noise_std``,
        for a position's and an amplitude's template (:func:`.information.residual_spectrum_factors`): the
        standard deviations are multiplied, the significances divided, by them.
    scores : (N, V, 5) array, optional
        Each view's pull on each atom (:func:`view_scores` of the fit's residuals).  With them the
        position's covariance is the sandwich ``F^-1 (sum_v g_v g_v^T) F^-1`` over the atom and its
        neighbours, views as independent clusters: what the residual that is there, whatever its
        structure within a view (misregistration, a support's texture, a misfit), does to a
        least-squares fit, instead of what white noise of its level would (``position_factor``
        and the L1 factor are then not used; the significance stays the cost of taking the atom
        out against the residual at its scale).
    targets : (N,) bool array, optional
        The atoms whose evidence is wanted (default all; every atom is a neighbour either way);
        the others' significance and precision are NaN.
    moved_pulls : dict, optional
        The profile of the cost along the depth axis beyond second order
        (:func:`.depth_profile.depth_profile_pulls`: offset in Å -> (N, 5) the residual's pull on each atom
        moved by it).  With them (and ``scores``) an atom is also open in depth where the cost,
        its neighbours and its other parameters re-fitted, rises by less than ``Z95^2`` noise
        variances (at the atom's scale) at some offset of half the hard core or more: a second
        place the views cannot tell from the first, or one they prefer (a fall in the cost with
        nothing else re-fitted, exact: the fit ended off its optimum there).
    device : torch device, optional
        Where the information and the local solves run
        (:func:`~gaussian_atoms_method.physics.devices.work_device`: a GPU where there is one, else
        the CPU); the neighbour search and the bookkeeping stay on the host.
    progress : callable, optional
        Called with the number of atoms each batch has read (a progress bar's count).
    field : :class:`~.information.DetectorField`, optional
        The detector's extent: each view informs a pair by the share of it on the detector (a
        film's edge atoms leave it in some views).  None: every atom is seen whole in every view.
    population : (N, 2, 2) array, optional
        Each Gaussian's prior precision on its width and amplitude
        (:func:`.population.population_precision`): added to the information the positions'
        precision and the depth profile are read from, the neighbours' widths and masses
        re-fitted within their population (not the significance, which asks what the neighbours
        could take up of an atom's image with every parameter free, nor the width's and mass's
        precision, against which an atom's width and mass are compared with their population's).

    Returns
    -------
    AtomEvidence
    """
    from gaussian_atoms_method.atoms.uncertainty import L1_EFFICIENCY_FACTOR

    positions = np.asarray(positions_A, dtype=np.float64).reshape(-1, 3)
    sigmas, amps = np.asarray(sigmas_A, np.float64).ravel(), np.asarray(amplitudes, np.float64).ravel()
    n = len(positions)
    if not (pixel_size_A > 0 and noise_std > 0):
        raise ValueError(f"need pixel_size_A > 0 and noise_std > 0, got {pixel_size_A} and {noise_std}")
    axes = np.asarray(detector_axes, dtype=np.float64)[:, :2, :]
    level = proof_level(n if targets is None else int(np.sum(targets)))
    if n == 0:
        empty = np.zeros(0)
        return AtomEvidence(
            empty, empty.astype(bool), np.zeros((0, 3)), empty, np.zeros((0, 3)), empty.astype(bool), level, hard_core_A
        )
    where = work_device(None, device) or torch.device("cpu")
    # the information within each atom and between the pairs that may couple
    sight = None if field is None else field.sight(axes)
    diagonal = pair_information(positions, positions, sigmas, sigmas, amps, amps, axes, pixel_size_A, where, sight)
    pairs = _pairs(positions, NEIGHBOUR_SEARCH_A)
    coupled = np.zeros(len(pairs), bool)
    if where.type != "cpu":  # a GPU's calls: few and large (DEVICE_PAIR_VIEWS)
        chunk_pairs = max(chunk_pairs, int(DEVICE_PAIR_VIEWS // max(len(axes), 1)))
    for start in range(0, len(pairs), chunk_pairs):
        i, j = pairs[start : start + chunk_pairs].T
        coupled[start : start + chunk_pairs] = (
            amplitude_coupling(positions[i], positions[j], sigmas[i], sigmas[j], axes, where) >= COUPLING_FLOOR
        )
    neighbours = pairs[coupled]
    wanted = np.flatnonzero(np.ones(n, bool) if targets is None else targets)
    # every block within each wanted atom's set, its neighbours' with each other too: the set's
    # information is then a principal submatrix of the whole one, positive definite as it is
    pairs = np.concatenate([neighbours, pairs_among_neighbours(neighbours, n, wanted, where)])
    blocks = np.zeros((len(pairs), 5, 5))
    for start in range(0, len(pairs), chunk_pairs):
        i, j = pairs[start : start + chunk_pairs].T
        blocks[start : start + chunk_pairs] = pair_information(
            positions[i], positions[j], sigmas[i], sigmas[j], amps[i], amps[j], axes, pixel_size_A, where, sight
        )
    variance = noise_std**2 * (L1_EFFICIENCY_FACTOR if loss == "l1" else 1.0)
    significance, width_variance, log_mass_variance = (np.full(n, np.nan) for _ in range(3))
    covariances = np.full((n, 3, 3), np.nan)
    fisher = np.full((n, 3, 3), np.nan)  # the noise's own covariance, where the sandwich states another
    offsets = sorted(moved_pulls) if moved_pulls else []
    rises, frozen = np.full((n, len(offsets)), np.inf), np.full((n, len(offsets)), np.inf)
    depth_axis_all = depth_axis_of(axes) if offsets else None
    scores_on = None if scores is None else torch.as_tensor(np.asarray(scores, np.float64), device=where)
    moved_on = (
        None
        if moved_pulls is None or scores is None
        else torch.as_tensor(np.stack([moved_pulls[o] for o in offsets]), dtype=torch.float64, device=where)
    )
    budget = HOST_BATCH_ELEMENTS if where.type == "cpu" else BATCH_ELEMENTS
    prior = (  # in the information's unit, a noise variance at the atoms' scale of one
        None
        if population is None
        else torch.as_tensor(np.asarray(population, np.float64) * variance * amplitude_factor**2, device=where)
    )
    table = (  # on the host each moved block is read once (depth_rises)
        None
        if moved_on is None or where.type != "cpu"
        else moved_blocks_of(
            (local for _, local in local_sets(wanted, neighbours, n, len(offsets), budget)),
            *(positions, sigmas, amps, axes, pixel_size_A, offsets, depth_axis_all, hard_core_A, sight),
        )
    )
    sets = local_information(wanted, neighbours, pairs, blocks, diagonal, len(offsets), budget, where)
    for atoms, local, info in sets:
        k, local_on = local.shape[1], torch.as_tensor(local, device=where)
        # a parameter the views do not fix (an amplitude of zero, a width at its bound) would make
        # the information singular: a ridge of 1e-9 of the diagonal leaves the rest unchanged
        info = info + torch.diag_embed(1e-9 * torch.diagonal(info, dim1=1, dim2=2).clamp_min(1e-300))
        prior_here = None if prior is None else prior[local_on]
        # the atom's rows of the inverse (the whole inverse where the depth profile solves through it)
        with_population = info if prior is None else with_prior(info, prior_here)
        whole = None if moved_on is None else spd_inverse(with_population)
        stated = spd_inverse_rows(with_population, 5) if whole is None else whole[:, :5]
        own = stated if prior is None else spd_inverse_rows(info, 5)
        if scores_on is not None:  # the sandwich, from the position's, width's and amplitude's rows: (C P^T)(P C^T)
            pulls = scores_on[local_on].permute(0, 2, 1, 3).reshape(len(atoms), scores.shape[1], 5 * k)  # (B, V, 5k)
            clusters = pulls.shape[1] / max(pulls.shape[1] - 1, 1)  # the views' small-sample factor
            rows = own @ pulls.transpose(1, 2)  # (B, 5, V)
            spread = (rows @ rows.transpose(1, 2) * clusters).cpu().numpy()
            if prior is not None:  # the positions' rows with the population's prior
                rows = stated[:, :3] @ pulls.transpose(1, 2)
                spread[:, :3, :3] = (rows @ rows.transpose(1, 2) * clusters).cpu()
            if moved_on is not None:  # the profile's unit (below)
                fisher[atoms] = stated[:, :3, :3].cpu().numpy()
        else:
            spread = own[:, :, :5].cpu().numpy().copy()  # not a view of the covariance
            spread[:, :3, :3] = stated[:, :3, :3].cpu().numpy()
        covariances[atoms], width_variance[atoms] = spread[:, :3, :3], spread[:, 3, 3]
        log_mass_variance[atoms] = _log_mass_variance(spread[:, 3:, 3:], sigmas[atoms], amps[atoms])
        if moved_on is not None:
            refitted, held = depth_rises(
                local, info, scores_on, moved_on, offsets, positions, sigmas, amps, axes, pixel_size_A,
                hard_core_A, depth_axis_all, table, whole, sight, prior_here,
            )  # fmt: skip
            rises[atoms], frozen[atoms] = refitted.cpu().numpy(), held.cpu().numpy()
        # taken out: the atom's amplitude against every parameter of its neighbours; the Schur complement
        # q^2 / [M^-1]_qq is the cost of taking it out, in noise variances, with M the information less the
        # atom's own position and width rows S: [M^-1]_qq = C_qq - C_qS C_SS^-1 C_Sq from the inverse C's rows
        c_qs = own[:, 4, :4, None]
        q_inverse = (own[:, 4, 4] - (c_qs * spd_solve(own[:, :4, :4], c_qs)).sum((1, 2))).cpu().numpy()
        q_variance = q_inverse * (noise_std * amplitude_factor) ** 2
        significance[atoms] = np.abs(amps[atoms]) / np.sqrt(np.maximum(q_variance, 1e-300))
        if progress is not None:
            progress(len(atoms))
    if scores is None:  # in units of the information's noise variance
        covariances = covariances * variance * position_factor**2
        width_variance = width_variance * variance * position_factor**2
        log_mass_variance = log_mass_variance * variance * amplitude_factor**2
    position_std = np.sqrt(np.clip(np.einsum("nii->ni", covariances), 0, None))
    values, vectors = np.linalg.eigh(np.nan_to_num(covariances))
    depth_half = np.where(np.isnan(covariances[:, 0, 0]), np.nan, Z95 * np.sqrt(np.clip(values[:, -1], 0, None)))
    depth_axis = vectors[:, :, -1] * np.sign(vectors[:, 2:3, -1] + 1e-300)  # pointing up the beam
    with np.errstate(invalid="ignore"):  # NaN: the atoms not asked for
        proven = significance >= level
    depth_open = wider_than_half_core(depth_half, hard_core_A)
    profile = rises / (noise_std * amplitude_factor) ** 2
    held = frozen / (noise_std * amplitude_factor) ** 2
    # A re-fit only lowers the cost: the exact rise with nothing re-fitted bounds it from above.
    # A re-fitted fall below -1.96^2 where that bound does not fall is the linearised re-fit
    # failing (two Gaussians nearly one, its steps far beyond their widths: on a small Au sphere
    # falls of -2,000 to -2,000,000), and the profile is not known there (NaN).  Where the bound
    # falls too, the views prefer the moved place outright: the fit ended off its optimum along
    # the beam (on the 54,000-atom Pd particle the profile fell at 11 of its 74 false atoms, 10
    # of them a move away from a true atom it missed, and at none of its 53,941 right ones).
    with np.errstate(invalid="ignore"):
        credible = profile >= -(Z95**2)
        profile = np.where(credible, np.minimum(profile, held), np.where(held < -(Z95**2), held, np.nan))
    # The profile's rises are read in the unit the interval states: to second order a rise is
    # d^2 / (the noise's variance along the axis), and the sandwich states the atom's variance
    # there as the residual its own views show, which a misfit raises above the noise's.  A place
    # within the stated 95% interval rises by under Z95^2 of the stated variance.  Never below
    # the noise's (the sandwich's 1/V scatter is not taken to close an atom).  On the 54,000-atom
    # Pd particle fitted on a CPU, the false atoms' stated depth half-widths had a median of
    # 0.26 Å, the right atoms' 0.13 (0.17 at their 99th percentile).
    scatter = np.ones(n)
    if scores is not None and offsets:
        noise_only = np.einsum("ni,nij,nj->n", depth_axis, fisher, depth_axis) * (noise_std * amplitude_factor) ** 2
        with np.errstate(invalid="ignore", divide="ignore"):
            scatter = np.where(noise_only > 0, np.maximum(values[:, -1] / noise_only, 1.0), 1.0)
    if offsets:  # a second place along the depth axis the views cannot tell from the first
        with np.errstate(invalid="ignore"):
            within = profile < Z95**2 * scatter[:, None]
        reach = np.max(np.where(within, np.abs(np.asarray(offsets))[None, :], 0.0), axis=1)
        depth_half = np.where(np.isnan(depth_half), np.nan, np.maximum(depth_half, reach))
        depth_open = depth_open | within.any(axis=1)
    return AtomEvidence(
        significance,
        proven,
        position_std,
        depth_half,
        depth_axis,
        depth_open,
        level,
        hard_core_A,
        np.asarray(offsets, dtype=np.float64),
        profile,
        np.sqrt(np.clip(width_variance, 0, None)),
        scatter,
        np.sqrt(np.clip(log_mass_variance, 0, None)),
    )


def _log_mass_variance(width_amplitude: np.ndarray, sigmas_A: np.ndarray, amplitudes: np.ndarray) -> np.ndarray:
    """(B,) the variance of each atom's log mass ``log q + 3 log sigma`` (the mass ``q (2 pi
    sigma^2)^(3/2)``) from its (B, 2, 2) covariance of (width, amplitude), to first order.

    >>> float(_log_mass_variance(np.array([[[0.0, 0.0], [0.0, 0.04]]]), np.ones(1), np.full(1, 2.0))[0])
    0.01
    """
    g = np.stack([3.0 / np.asarray(sigmas_A, np.float64), 1.0 / np.asarray(amplitudes, np.float64)], axis=1)
    return np.einsum("bi,bij,bj->b", g, width_amplitude, g)


EVIDENCE_SCORES = (
    "proven",
    "open",
    "depth_open",
    "proven_found",
    "trusted_share_of_truth",
    "open_share_of_false",
    "open_share_of_misses",
    "open_share_of_disagreement",
    "coverage_95_xyz",
    "depth_coverage_95",
)
"""The keys of :func:`evidence_scores` a run says on a line of their own before its scores
(:func:`gaussian_atoms_method.engine.results.write_results`; ``evaluation.json`` holds both);
``precision_floor_A`` is said with the scores."""


def evidence_scores(
    pred,
    truth,
    radius_A: float = 0.75,
    mean_shift: bool = False,
    pred_counted: np.ndarray | None = None,
    truth_counted: np.ndarray | None = None,
) -> dict:
    """Whether each atom's stated evidence holds against the truth (``pred``, ``truth``:
    :class:`~.atom_set.AtomSet`, the first with its evidence).

    * ``coverage_95_xyz``: the share of found atoms whose error along x, y, z lies within their
      stated 95% interval (``1.96 position_std_A``; 0.95 if the statement were exact);
      ``depth_coverage_95``: within the depth interval (``depth_halfwidth_A``, along the beam);
    * ``proven_found``: the share of the atoms not called open (``trusted``) that lie on a true
      one; ``trusted_share_of_truth``: the share of the true atoms a trusted atom lies on (what a
      user who keeps only the trusted atoms has of the truth);
    * ``open_share_of_false``: the share of false atoms (on no true one) called open
      (:func:`.trust.open_atoms`: not proven, open in depth, not one atom's width or mass, or open in element);
      ``open_share_of_misses``: the share of missed true atoms with an open atom within twice
      ``radius_A`` (the atom the data placed elsewhere, or could not prove);
      ``open_share_of_disagreement``: both together.  The two sides split the atoms alike: an
      atom proven but open in depth counts as open in both;
    * ``precision_floor_A``: the error along x, y, z the stated precision does not hold
      (:func:`.calibration.precision_floor_A`): on a replica, what to give the real run.

    ``pred_counted`` (N,) and ``truth_counted`` (M,) bool, for a region cut from a larger whole:
    every atom is matched, only the counted ones are scored (an atom inside the region whose
    partner lies just outside it is neither false nor missed).
    """
    from scipy.spatial import cKDTree

    from gaussian_atoms_method.atoms.matching import global_shift, match_atoms
    from gaussian_atoms_method.atoms.trust import open_atoms

    shift = global_shift(pred.positions, truth.positions, radius_A) if mean_shift else np.zeros(3)
    positions = pred.positions + shift
    pi, ti = match_atoms(positions, truth.positions, radius_A)
    error = positions[pi] - truth.positions[ti]
    counted = np.ones(len(pred), bool) if pred_counted is None else np.asarray(pred_counted, bool)
    truth_in = np.ones(len(truth), bool) if truth_counted is None else np.asarray(truth_counted, bool)
    is_open = open_atoms(pred)
    matched = np.zeros(len(pred), dtype=bool)
    matched[pi] = True
    missed = np.ones(len(truth), dtype=bool)
    missed[ti] = False
    missed &= truth_in
    near_open = np.zeros(int(missed.sum()), dtype=bool)
    if is_open.any() and missed.any():
        distance, _ = cKDTree(positions[is_open]).query(truth.positions[missed], distance_upper_bound=2 * radius_A)
        near_open = np.isfinite(distance)
    false = ~matched & counted
    closed = ~is_open & counted
    on_trusted = truth_in[ti] & ~is_open[pi]  # the counted true atoms a trusted atom lies on
    scored = truth_in[ti]  # the matched pairs scored: their true atom counted, as the found are
    pi, ti, error = pi[scored], ti[scored], error[scored]
    scores = {
        "proven": int(pred.proven[counted].sum()),
        "open": int((pred.proven[counted] == 0).sum()),
        "depth_open": int(pred.depth_open[counted].sum()),
        "proven_found": float(matched[closed].mean()) if closed.any() else None,
        "trusted_share_of_truth": float(on_trusted.sum() / truth_in.sum()) if truth_in.any() else None,
        "open_share_of_false": float(is_open[false].mean()) if false.any() else None,
        "open_share_of_misses": float(near_open.mean()) if missed.any() else None,
        "open_share_of_disagreement": (
            float((is_open[false].sum() + near_open.sum()) / (false.sum() + missed.sum()))
            if false.any() or missed.any()
            else None
        ),
    }
    if len(pi) and pred.position_std_A is not None:
        scores["coverage_95_xyz"] = np.mean(np.abs(error) <= Z95 * pred.position_std_A[pi], axis=0).tolist()
        scores["precision_floor_A"] = precision_floor_A(error, pred.position_std_A[pi]).tolist()
    if len(pi) and pred.depth_halfwidth_A is not None:
        scores["depth_coverage_95"] = float(np.mean(np.abs(error[:, 2]) <= pred.depth_halfwidth_A[pi]))
    return scores
