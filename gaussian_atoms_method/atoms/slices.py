"""Central slices of a result's potential with its atoms (and the truth's) near each, and their picture."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gaussian_atoms_method.atoms.atom_set import AtomSet

#: (axis normal to the slice, the two in-plane axes), for the xy, xz and yz slices.
SLICES = ((2, 0, 1), (1, 0, 2), (0, 1, 2))


def potential_on_plane(
    atoms: AtomSet,
    normal_axis: int,
    offset_A: float,
    axis_u: int,
    axis_v: int,
    coords_u_A: np.ndarray,
    coords_v_A: np.ndarray,
    device=None,
) -> np.ndarray:
    """The Gaussians' potential on a plane ``x[normal_axis] = offset_A``.

    Parameters
    ----------
    atoms : AtomSet with sigmas and amplitudes
    normal_axis, axis_u, axis_v : int
        World axes (0 x, 1 y, 2 z): the plane's normal and its two in-plane axes.
    coords_u_A, coords_v_A : (U,), (V,) arrays
        Sample positions along the in-plane axes, Å.

    device : torch device, optional
        Where the product runs (float64; a GPU run's own device): numpy's by default.

    Returns
    -------
    (U, V) array, in the amplitudes' units.  Each Gaussian is separable, so the plane is one
    matrix product over the atoms within 4 sigma of it.
    """
    if atoms.sigmas is None or atoms.amplitudes is None:
        raise ValueError("the potential needs each atom's sigma_A and amplitude")
    pos, sig, amp = atoms.positions, atoms.sigmas, atoms.amplitudes
    near = np.abs(pos[:, normal_axis] - offset_A) < 4 * sig
    pos, sig, amp = pos[near], sig[near], amp[near]
    weight = amp * np.exp(-((pos[:, normal_axis] - offset_A) ** 2) / (2 * sig**2))
    gu = np.exp(-((coords_u_A[None, :] - pos[:, axis_u, None]) ** 2) / (2 * sig[:, None] ** 2))
    gv = np.exp(-((coords_v_A[None, :] - pos[:, axis_v, None]) ** 2) / (2 * sig[:, None] ** 2))
    if device is None or str(device) == "cpu":
        return (weight[:, None] * gu).T @ gv
    import torch

    return (torch.as_tensor(weight[:, None] * gu, device=device).T @ torch.as_tensor(gv, device=device)).cpu().numpy()


PANEL_SAMPLES = 800
"""A slice is sampled at most this many times across: twice the pixels a panel of the figure
shows (5 in at 90 dpi, about 400), so a wide particle's slices cost no more than the picture
can show."""


@dataclass
class SlicePlanes:
    """Three central slices of a result's potential and the atoms to mark on them
    (:func:`slice_planes`), in Å: what :func:`~gaussian_atoms_method.atoms.pictures.draw_slices`
    draws, plain arrays (a child process draws them, :mod:`.picture_process`)."""

    axes: tuple
    """Each slice's (normal, u, v) world axes (:data:`SLICES`)."""
    planes: list
    """Three (U, V) potentials, one per slice."""
    extents: list
    """Each plane's (left, right, bottom, top) in Å, for ``imshow``."""
    centre_A: np.ndarray
    slab_A: float
    true_points: list
    """Per slice, the (v, u) positions of the true atoms within ``slab_A`` of it (None without a truth)."""
    predicted_points: list
    """Per slice, the (v, u) positions of the predicted atoms within ``slab_A`` of it."""


def slice_planes(
    pred: AtomSet, truth: AtomSet | None = None, spacing_A: float = 0.1, slab_A: float = 1.0, device=None
) -> SlicePlanes:
    """Three central slices (xy, xz, yz through the atoms' median) of the predicted potential,
    sampled every ``spacing_A``, or coarser where a slice would take more than
    :data:`PANEL_SAMPLES` samples, the products on ``device`` (:func:`potential_on_plane`); and
    the predicted and true atoms within ``slab_A`` of each.  A predicted atom matched to a true
    one is taken with it (by the true atom's distance to the slice), so a lone marker is a real
    miss or a false atom, not the slab's edge."""
    if len(pred) == 0:
        raise ValueError("no predicted atoms to draw")
    pred_slab_position = pred.positions.copy()
    if truth is not None and len(truth):
        from gaussian_atoms_method.atoms.matching import match_atoms

        pred_idx, true_idx = match_atoms(pred.positions, truth.positions, 0.75)
        pred_slab_position[pred_idx] = truth.positions[true_idx]
    centre = np.median(pred.positions, axis=0)
    reference = truth.positions if truth is not None and len(truth) else pred.positions
    half = float(np.max(np.abs(reference - centre))) + 3.0
    spacing_A = max(spacing_A, 2 * half / PANEL_SAMPLES)
    coords = np.arange(-half, half + spacing_A / 2, spacing_A)
    planes, extents, true_points, predicted_points = [], [], [], []
    for n, u, v in SLICES:
        planes.append(potential_on_plane(pred, n, centre[n], u, v, coords + centre[u], coords + centre[v], device))
        extents.append((centre[v] - half, centre[v] + half, centre[u] + half, centre[u] - half))
        if truth is not None:
            near = np.abs(truth.positions[:, n] - centre[n]) < slab_A
            true_points.append(truth.positions[near][:, [v, u]])
        else:
            true_points.append(None)
        near = np.abs(pred_slab_position[:, n] - centre[n]) < slab_A
        predicted_points.append(pred.positions[near][:, [v, u]])
    return SlicePlanes(SLICES, planes, extents, centre, float(slab_A), true_points, predicted_points)


def write_slices_png(
    pred: AtomSet,
    output: Path,
    truth: AtomSet | None = None,
    spacing_A: float = 0.1,
    slab_A: float = 1.0,
    title: str = "",
    device=None,
) -> Path:
    """The three central slices of :func:`slice_planes` with the predicted atoms (open circles)
    and true atoms (crosses) within ``slab_A`` of each slice overlaid
    (:func:`~gaussian_atoms_method.atoms.pictures.draw_slices`); written atomically (complete
    or absent)."""
    from gaussian_atoms_method.atoms.pictures import draw_slices

    return draw_slices(slice_planes(pred, truth, spacing_A, slab_A, device), output, title)
