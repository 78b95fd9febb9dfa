"""The cost's profile along the depth axis beyond second order: each atom (and the column it would
move with) moved along the direction the views fix least, by 1, 2 and 3 halves of the hard core
either way, everything else of its set re-fitted, linearised about the moved places
(:func:`.evidence.atom_evidence`'s ``depth_open``: a second place the views cannot tell from the
first)."""

from __future__ import annotations

import numpy as np
import torch

from gaussian_atoms_method.atoms.information import pair_information, view_scores


def depth_axis_of(detector_axes: np.ndarray) -> np.ndarray:
    """(3,) the direction the views fix least: the smallest eigenvector of ``sum_v P_v^T P_v``
    (the beam of the zero tilt for a symmetric single-axis series), pointing up."""
    axes = np.asarray(detector_axes, dtype=np.float64)[:, :2, :]
    values, vectors = np.linalg.eigh(np.einsum("vki,vkj->ij", axes, axes))
    axis = vectors[:, 0]
    return axis * (1.0 if axis[2] >= 0 else -1.0)


def depth_profile_pulls(
    positions_A, sigmas_A, amplitudes, detector_axes, residuals, pixel_size_A, centre_px, hard_core_A
) -> dict:
    """For the cost's profile along the depth axis beyond second order (:func:`.evidence.atom_evidence`'s
    ``moved_pulls``): offset (Å) -> (N, 5) the residual's pull on each atom moved by it along
    :func:`depth_axis_of`, every atom's (a neighbour beyond those asked for may move with one in
    a column, :func:`depth_rises`).  The offsets are 1, 2 and 3 halves
    of the hard core either way: where an atom could sit instead of where it is (the Ta model's
    displaced atoms are 0.75-1.5 Å from ours, mostly along the beam)."""
    positions = np.asarray(positions_A, dtype=np.float64).reshape(-1, 3)
    axis = depth_axis_of(detector_axes)
    out = {}
    for k in (-3, -2, -1, 1, 2, 3):
        offset = 0.5 * k * hard_core_A
        out[offset] = view_scores(
            positions + offset * axis,
            np.asarray(sigmas_A),
            np.asarray(amplitudes),
            detector_axes,
            residuals,
            pixel_size_A,
            centre_px,
        ).sum(axis=1)
    return out


def _columns(local: np.ndarray, positions: np.ndarray, offsets, axis: np.ndarray, hard_core_A) -> np.ndarray:
    """(B, M, k) bool: the atoms of each set ``local`` (B, k) moved with its atom ``local[:, 0]``
    by each of the M ``offsets`` along ``axis``: the atom, and in turn every atom of the set whose
    place a moved one would come within the hard core of.  Two atoms cannot share a place, but a
    column can shift along the beam as one: the missing wedge's ambiguity is that of a column (on a
    replica of a Ta sub-area the misses lay 0.8-1.4 Å along the beam from their atoms, the true
    place within the hard core of a neighbour that had moved with them)."""
    b, k = local.shape
    column = np.zeros((b, len(offsets), k), bool)
    column[:, :, 0] = True
    if hard_core_A is None or k == 1:
        return column
    here = positions[local]  # (B, k, 3)
    shifted = here[:, None] + np.asarray(offsets, np.float64)[None, :, None, None] * axis  # (B, M, k, 3)
    close = np.linalg.norm(shifted[:, :, :, None] - here[:, None, None], axis=-1) < hard_core_A  # (B, M, i, j)
    for _ in range(k):
        grown = column | np.any(close & column[..., :, None], axis=2)
        if np.array_equal(grown, column):
            break
        column = grown
    return column


def depth_rises(
    local, info, scores, moved, offsets, positions, sigmas, amps, axes, pixel_size_A, hard_core_A, axis, table=None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Two (B, M): for each atom ``local[:, 0]`` and each of the M ``offsets``, how much the
    least-squares cost rises (pixel sums, in projection units squared) when the atom is moved by
    it along the depth axis, with it the atoms whose places it would take (:func:`_columns`: a
    column shifted as one), and every other parameter of the set ``local`` (B, k) is re-fitted
    (linearised about the moved places; ``info`` (B, 5k, 5k): the local information, pixel sums,
    the atom first; ``scores`` (N, V, 5) the views' pulls, ``moved`` (M, N, 5) the pulls on the
    atoms moved by each offset, tensors on ``info``'s device; ``axis``: :func:`depth_axis_of` the
    views, the direction moved along).

    With ``G`` the moved atoms, ``g_i'`` atom i's image at its new place and ``r`` the residual,
    the cost before the re-fit changes by ``-2 <r, sum_G (g_i' - g_i)> + |sum_G (g_i' - g_i)|^2``;
    every overlap is a pair's information block (a pair moved together keeps its own), and the
    re-fit is one Gauss-Newton step from the moved places with each moved atom's place along the
    axis held.  The second is that change before the re-fit, exact (no linearisation): where it
    falls the views prefer the moved place even with nothing else re-fitted.

    ``table``: a :class:`MovedBlocks` that holds the batch's blocks of moved atoms (the host's
    way: each block read once); without it they are read here, on ``info``'s device (a GPU's way:
    reading a block again costs it less than looking it up on the host)."""
    b, k = local.shape
    m = len(offsets)
    on = dict(dtype=torch.float64, device=info.device)
    column = _columns(local, positions, offsets, axis, hard_core_A)
    # each moved atom at its new place against every atom of its set at its old one
    bi, mi, ii = np.nonzero(column)
    cross = torch.zeros((b, m, k, k, 5, 5), **on)  # [i moved, j]: rows i's parameters at its new place
    if table is not None:
        cross[bi, mi, ii] = torch.as_tensor(table.blocks(local[bi, ii], mi, local[bi]), **on)
    else:  # read here, on the information's device
        moved_places = positions[local[bi, ii]] + np.asarray(offsets, np.float64)[mi, None] * axis
        here = positions[local]
        cross[bi, mi, ii] = torch.as_tensor(
            pair_information(
                np.repeat(moved_places, k, axis=0),
                here[bi].reshape(-1, 3),
                np.repeat(sigmas[local[bi, ii]], k),
                sigmas[local[bi]].ravel(),
                np.repeat(amps[local[bi, ii]], k),
                amps[local[bi]].ravel(),
                axes,
                pixel_size_A,
                device=info.device,
            ),
            **on,
        ).reshape(-1, k, 5, 5)
    blocks = info.reshape(b, k, 5, k, 5).permute(0, 1, 3, 2, 4)  # [i, j]: rows i's parameters
    g = torch.as_tensor(column, device=info.device)
    local_on = torch.as_tensor(local, device=info.device)
    q = torch.as_tensor(amps, **on)[local_on]  # (B, k)
    qg = q[:, None] * g  # the moved atoms' masses, zero for the others
    pull_now = scores[local_on].sum(dim=2)  # (B, k, 5): J^T r at the fit
    pull_moved = moved[:, local_on].permute(1, 0, 2, 3)  # (B, M, k, 5): at the moved places
    # -2 <r, dg> + |dg|^2, dg = sum over the moved of (g_i' - g_i)
    rd = (qg * (pull_moved[..., 4] - pull_now[:, None, :, 4])).sum(-1)
    c44 = cross[..., 4, 4]
    dd = torch.einsum("bmi,bmj,bmij->bm", qg, qg, 2 * blocks[:, None, :, :, 4, 4] - c44 - c44.transpose(2, 3))
    # the pull at the moved places: <r - dg, dg_j/dp>, atom j at its new place or its old one
    own = blocks[..., :, 4]  # (B, j, i, 5): <dg_j/dp, g_i / q_i>
    on_moved = torch.einsum("bmi,bmjip->bmjp", qg, own[:, None] - cross[..., :, 4])
    on_still = torch.einsum("bmi,bmijp->bmjp", qg, cross[..., 4, :]) - torch.einsum("bmi,bjip->bmjp", qg, own)
    gj = g[..., None]
    pull = (torch.where(gj, pull_moved, pull_now[:, None]) - torch.where(gj, on_moved, on_still)).reshape(b, m, 5 * k)
    # the information at the moved places: a pair moved together, or left together, keeps its block
    gi_, gj_ = g[..., :, None], g[..., None, :]
    with_move = torch.where(
        (gi_ == gj_)[..., None, None],
        blocks[:, None],
        torch.where((gi_ & ~gj_)[..., None, None], cross, cross.transpose(2, 3).transpose(-1, -2)),
    )
    del cross
    with_move = with_move.permute(0, 1, 2, 4, 3, 5).reshape(b, m, 5 * k, 5 * k)
    # positions turned to two directions across the axis and the axis; each moved atom's place
    # along the axis held (its row and column cut out: a unit diagonal and a zero pull)
    basis = torch.as_tensor(np.linalg.qr(np.c_[axis, np.eye(3)])[0][:, [1, 2, 0]].T, **on)
    held = torch.zeros((b, m, k, 5), dtype=torch.bool, device=info.device)
    held[..., 2] = g
    held = held.reshape(b, m, 5 * k)

    def turned(information):  # each atom's position block turned to the basis: (5k, 5k) blockwise
        blocks = information.reshape(*information.shape[:-2], k, 5, k, 5).clone()
        blocks[..., :3, :, :] = torch.einsum("ab,...ibjc->...iajc", basis, blocks[..., :3, :, :])
        blocks[..., :, :, :3] = torch.einsum("...ibjc,dc->...ibjd", blocks[..., :, :, :3], basis)
        return blocks.reshape(information.shape)

    def turned_pull(gradient):
        pulls = gradient.reshape(*gradient.shape[:-1], k, 5).clone()
        pulls[..., :3] = pulls[..., :3] @ basis.T
        return pulls.reshape(gradient.shape)

    def refit(turned_information, turned_gradient, held):
        rhs = torch.where(held, 0.0, turned_gradient)
        cut = held[..., :, None] | held[..., None, :]
        system = torch.where(cut, 0.0, turned_information) + torch.diag_embed(held.double())
        return (rhs * torch.linalg.solve(system, rhs[..., None])[..., 0]).sum(-1)

    # the fit as it is, with the places held that an offset moves: offsets that move the same
    # atoms hold the same places (on the Au particle 2.9 of 6 differ), each solved once
    patterns = np.c_[np.repeat(np.arange(b), m), column.reshape(b * m, k)]
    _, once, again = np.unique(patterns, axis=0, return_index=True, return_inverse=True)
    atom_of = torch.as_tensor(once // m, device=info.device)
    baseline = refit(
        turned(info)[atom_of],
        turned_pull(pull_now.reshape(b, 5 * k))[atom_of],
        held.reshape(b * m, 5 * k)[torch.as_tensor(once)],
    )[torch.as_tensor(again.ravel(), device=info.device)].reshape(b, m)
    frozen = -2 * rd + dd
    return frozen - refit(turned(with_move), turned_pull(pull), held) + baseline, frozen


class MovedBlocks:
    """The information blocks of atoms moved along the depth axis against atoms where they are,
    each read once: ``pair_information`` of atom ``i`` at ``positions[i] + offsets[m] axis`` and
    atom ``j`` at its place, for every (i, m, j) of ``moved`` (R,), ``offset_index`` (R,) and
    ``others`` (R, k) (each moved atom against every atom of its set).  One moved atom meets the
    same atom in the sets of all the atoms of its column: on the Au particle each block is asked for
    2.5 times on average."""

    def __init__(self, moved, offset_index, others, positions, sigmas, amps, axes, pixel_size_A, offsets, axis):
        self.n, self.m = len(positions), len(offsets)
        others = np.asarray(others).reshape(len(moved), -1)
        keys = np.unique(self._keys(np.asarray(moved)[:, None], np.asarray(offset_index)[:, None], others))
        i, rest = np.divmod(keys, self.m * self.n)
        m, j = np.divmod(rest, self.n)
        self.keys = keys
        self.table = np.empty((len(keys), 5, 5))
        shift = np.asarray(offsets, np.float64)[m, None] * np.asarray(axis, np.float64)
        for start in range(0, len(keys), TABLE_CHUNK):
            part = slice(start, start + TABLE_CHUNK)
            ii, jj = i[part], j[part]
            self.table[part] = pair_information(
                positions[ii] + shift[part],
                positions[jj],
                sigmas[ii],
                sigmas[jj],
                amps[ii],
                amps[jj],
                axes,
                pixel_size_A,
            )

    def _keys(self, moved, offset_index, others):
        return (moved * self.m + offset_index) * self.n + others

    def blocks(self, moved, offset_index, others) -> np.ndarray:
        """(R, k, 5, 5) the blocks of ``moved`` (R,) atoms moved by their ``offset_index`` (R,)
        against ``others`` (R, k) (each asked for when the table was made)."""
        keys = self._keys(np.asarray(moved)[:, None], np.asarray(offset_index)[:, None], np.asarray(others))
        return self.table[np.searchsorted(self.keys, keys)]


TABLE_CHUNK = 65536
"""The moved pairs :class:`MovedBlocks` reads at once."""


def moved_blocks_of(sets, positions, sigmas, amps, axes, pixel_size_A, offsets, axis, hard_core_A) -> MovedBlocks:
    """The :class:`MovedBlocks` every set of ``sets`` (each (B, k), the atom first, as
    :func:`~.information.local_sets` yields them) asks for in :func:`depth_rises`."""
    moved, offset_index, others = [], [], []
    for local in sets:
        bi, mi, ii = np.nonzero(_columns(local, positions, offsets, axis, hard_core_A))
        moved.append(local[bi, ii])
        offset_index.append(mi)
        others.append(local[bi].reshape(len(bi), -1))
    k = max((o.shape[1] for o in others), default=1)
    padded = [np.pad(o, ((0, 0), (0, k - o.shape[1])), mode="edge") for o in others]  # repeats ask nothing new
    picked = (np.concatenate(moved), np.concatenate(offset_index), np.concatenate(padded))
    return MovedBlocks(*picked, positions, sigmas, amps, axes, pixel_size_A, offsets, axis)
