"""How well a fit predicts views it never saw: two-fold cross-validation over a tilt series.

A measured series has no truth to score against, and a fit's own residual always prefers more
parameters: extra Gaussians beside the atoms explain a probe's tails as well as a kernel does.
Views held out of the fit tell them apart.  :func:`split_views` writes the even and the odd
views as two tilt series; a fit of one predicts the other
(:func:`~gaussian_atoms_method.atoms.view_prediction.predicted_views`: the fit's Gaussians, atoms
and non-atoms, projected and convolved with its kernel), and
:func:`~gaussian_atoms_method.atoms.view_prediction.held_out_rms` scores it with one constant per
view fitted on the held-out view itself
(the fit's learned backgrounds belong to the views it saw).

On the Ta film (area 23) the published model with 33% of the intensity in a 3 Å halo predicts
the odd views from parameters fitted on the even ones at 2794 (rms, input units); our fit of the
even views with no kernel, at 2842.  Pure numpy and torch.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from gaussian_atoms_method.atoms.atom_set import AtomSet
from gaussian_atoms_method.atoms.merge import merged_values
from gaussian_atoms_method.atoms.view_prediction import interior, predicted_views


def split_views(series, out_dir: str | Path) -> tuple[Path, Path]:
    """Write the even-indexed and the odd-indexed views of ``series`` (a
    :class:`dataparsers.tilt_series_format.TiltSeries`) as two tilt-series directories under
    ``out_dir`` (``even``, ``odd``), with its geometry (Euler angles and their convention
    included), species and truth; returns their paths."""
    from dataparsers.tilt_series_format import write_tilt_series
    from gaussian_atoms_method.atoms.atom_set import read_atoms

    truth = read_atoms(series.truth_path) if series.truth_path is not None else None
    out = []
    for name, start in (("even", 0), ("odd", 1)):
        out.append(
            write_tilt_series(
                Path(out_dir) / name,
                series.projections[start::2],
                (series.angles_deg if series.euler_deg is None else series.euler_deg)[start::2],
                series.pixel_size_A,
                truth=truth,
                origin_A=series.origin_A,
                tilt_axis=series.tilt_axis,
                centre_px=series.centre_px,
                tilt_axis_angle_deg=series.tilt_axis_angle_deg,
                species=series.species,
                euler_convention=series.euler_convention,
            )
        )
    return out[0], out[1]


def _residuals(atoms: AtomSet, series_list, kernel_weights, interior_px) -> list[np.ndarray]:
    """Measured minus :func:`predicted_views` of ``atoms`` in each series, over the interior."""
    return [
        interior(
            np.asarray(series.projections, dtype=np.float64) - predicted_views(atoms, series, kernel_weights),
            interior_px,
        )
        for series in series_list
    ]


def pair_merge_costs(
    atoms: AtomSet, pairs: np.ndarray, fitted, held, kernel_weights=None, interior_px: tuple[int, int] = (0, 0)
) -> np.ndarray:
    """What merging each pair of Gaussians costs, on the views the fit saw and on views it did not.

    Each pair is replaced by one Gaussian at the mass-weighted centre with the mass-weighted width,
    its mass scaled to fit the ``fitted`` views best with every other Gaussian held; the rise in
    the sum of squared residuals (after one constant per view, over the detector's interior) is
    read on ``fitted`` and, with the same merged Gaussian, on ``held``.  A pair the data demand
    keeps its cost on the held-out views; one that fits the fitted views' own errors loses it.

    Parameters
    ----------
    atoms : AtomSet
        Every Gaussian of a fit of ``fitted``
        (:func:`~gaussian_atoms_method.atoms.view_prediction.run_gaussians`), Å, with sigmas and
        amplitudes.
    pairs : (K, 2) int array
        Indices into ``atoms``.
    fitted, held : tilt series
        The views the fit saw and views it did not (:func:`split_views`).

    Returns
    -------
    (K, 2) array: the cost on ``fitted`` and on ``held``, squared data units.
    """
    residuals = _residuals(atoms, (fitted, held), kernel_weights, interior_px)
    squares = [float((residual**2).sum()) for residual in residuals]
    pos, sig, amp = (
        torch.as_tensor(np.asarray(v, dtype=np.float64)) for v in (atoms.positions, atoms.sigmas, atoms.amplitudes)
    )
    one_cluster = torch.zeros(2, dtype=torch.long)
    costs = np.zeros((len(pairs), 2))
    for k, ij in enumerate(np.asarray(pairs, dtype=np.int64).reshape(-1, 2)):
        pair = AtomSet(positions=pos[ij].numpy(), sigmas=sig[ij].numpy(), amplitudes=amp[ij].numpy())
        centre, width, height = merged_values(pos[ij], sig[ij], amp[ij], one_cluster, 1)  # mass-weighted, mass kept
        merged = AtomSet(positions=centre.numpy(), sigmas=width.numpy(), amplitudes=height.numpy())
        scale = None
        for col, (series, residual) in enumerate(zip((fitted, held), residuals)):
            # the residual with the pair taken out
            without = residual + interior(predicted_views(pair, series, kernel_weights), interior_px)
            one = interior(predicted_views(merged, series, kernel_weights), interior_px)
            if scale is None:
                scale = float((without * one).sum() / max((one * one).sum(), 1e-300))
            costs[k, col] = float(((without - scale * one) ** 2).sum()) - squares[col]
    return costs


def move_costs(
    atoms: AtomSet,
    indices: np.ndarray,
    targets_A: np.ndarray,
    fitted,
    held,
    kernel_weights=None,
    interior_px: tuple[int, int] = (0, 0),
) -> np.ndarray:
    """What moving each of some Gaussians elsewhere costs, on the views the fit saw and on views
    it did not: the rise in the sum of squared residuals (after one constant per view, over the
    detector's interior) when Gaussian ``indices[k]`` alone moves to ``targets_A[k]``, its width
    and mass kept, every other Gaussian held.  Negative on ``held``: the unseen views prefer the
    target.  Where the data fix an atom's place, a move of an ångström costs on both; where they
    hardly tell two places apart (along the missing wedge), it costs little either way.

    Parameters
    ----------
    atoms, fitted, held, kernel_weights, interior_px
        As :func:`pair_merge_costs` takes them.
    indices : (K,) int array
        Into ``atoms``.
    targets_A : (K, 3) array
        Where each goes, Å in ``atoms``' frame.

    Returns
    -------
    (K, 2) array: the cost on ``fitted`` and on ``held``, squared data units.
    """
    residuals = _residuals(atoms, (fitted, held), kernel_weights, interior_px)
    targets_A = np.asarray(targets_A, dtype=np.float64).reshape(-1, 3)
    costs = np.zeros((len(targets_A), 2))
    for k, (i, target) in enumerate(zip(np.asarray(indices, dtype=np.int64), targets_A)):
        width, height = atoms.sigmas[i : i + 1], atoms.amplitudes[i : i + 1]
        before = AtomSet(positions=atoms.positions[i : i + 1], sigmas=width, amplitudes=height)
        after = AtomSet(positions=target[None], sigmas=width, amplitudes=height)
        for col, (series, residual) in enumerate(zip((fitted, held), residuals)):
            change = interior(
                predicted_views(after, series, kernel_weights) - predicted_views(before, series, kernel_weights),
                interior_px,
            )
            costs[k, col] = float((change * change).sum() - 2.0 * (residual * change).sum())
    return costs
