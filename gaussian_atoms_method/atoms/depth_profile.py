"""The cost's profile along the depth axis beyond second order: each atom (and the column it would
move with) moved along the direction the views fix least, by 1, 2 and 3 halves of the hard core
either way, everything else of its set re-fitted, linearised about the moved places
(:func:`.evidence.atom_evidence`'s ``depth_open``: a second place the views cannot tell from the
first)."""

from __future__ import annotations

import numpy as np
import torch

from gaussian_atoms_method.atoms.information import pair_blocks, pair_information, view_planes, view_scores
from gaussian_atoms_method.atoms.population import with_prior
from gaussian_atoms_method.physics.arrays import unique_keys
from gaussian_atoms_method.physics.spd import spd_inverse, spd_solve


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


def _columns(
    local: np.ndarray, positions: np.ndarray, offsets, axis: np.ndarray, hard_core_A, device=None
) -> np.ndarray:
    """(B, M, k) bool: the atoms of each set ``local`` (B, k) moved with its atom ``local[:, 0]``
    by each of the M ``offsets`` along ``axis``: the atom, and in turn every atom of the set whose
    place a moved one would come within the hard core of.  Two atoms cannot share a place, but a
    column can shift along the beam as one: the missing wedge's ambiguity is that of a column (on
    a replica of a Ta sub-area the misses lay 0.8-1.4 Å along the beam from their atoms, the true
    place within the hard core of a neighbour that had moved with them).  Found in torch on
    ``device`` (default the CPU): on a GPU, numpy on the host had taken 14 of the 50 s a
    76,000-atom particle's evidence took."""
    b, k = local.shape
    if hard_core_A is None or k == 1:
        column = np.zeros((b, len(offsets), k), bool)
        column[:, :, 0] = True
        return column
    on = dict(dtype=torch.float64, device=device or "cpu")
    here = torch.as_tensor(positions[local], **on)  # (B, k, 3): the batch's atoms only sent to the device
    step = torch.as_tensor(np.asarray(offsets, np.float64)[:, None] * np.asarray(axis, np.float64), **on)  # (M, 3)
    shifted = here[:, None] + step[None, :, None]  # (B, M, k, 3)
    close = torch.linalg.vector_norm(shifted[:, :, :, None] - here[:, None, None], dim=-1) < hard_core_A  # (B, M, i, j)
    column = torch.zeros((b, len(offsets), k), dtype=torch.bool, device=on["device"])
    column[:, :, 0] = True
    for _ in range(k):
        grown = column | torch.any(close & column[..., :, None], dim=2)
        if torch.equal(grown, column):
            break
        column = grown
    return column.cpu().numpy()


def depth_rises(
    local,
    info,
    scores,
    moved,
    offsets,
    positions,
    sigmas,
    amps,
    axes,
    pixel_size_A,
    hard_core_A,
    axis,
    table=None,
    covariance=None,
    sight=None,
    prior=None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Two (B, M): for each atom ``local[:, 0]`` and each of the M ``offsets``, how much the
    least-squares cost rises (pixel sums, in projection units squared) when the atom is moved by
    it along the depth axis, with it the atoms whose places it would take (:func:`_columns`: a
    column shifted as one), and every other parameter of the set ``local`` (B, k) is re-fitted
    (linearised about the moved places; ``info`` (B, 5k, 5k): the local information, pixel sums,
    the atom first; ``scores`` (N, V, 5) the views' pulls, ``moved`` (M, N, 5) the pulls on the
    atoms moved by each offset, tensors on ``info``'s device; ``axis``: :func:`depth_axis_of` the
    views, the direction moved along; ``covariance``: ``info``'s inverse where the caller has it;
    ``prior`` (B, k, 2, 2): each atom's population precision on its width and amplitude
    (:func:`~.population.population_precision`, in ``info``'s units), with which the set is
    re-fitted: then ``covariance`` must be the inverse of ``info`` with it).

    With ``G`` the moved atoms, ``g_i'`` atom i's image at its new place and ``r`` the residual,
    the cost before the re-fit changes by ``-2 <r, sum_G (g_i' - g_i)> + |sum_G (g_i' - g_i)|^2``;
    every overlap is a pair's information block (a pair moved together keeps its own), and the
    re-fit is one Gauss-Newton step from the moved places with each moved atom's place along the
    axis held.  The second is that change before the re-fit, exact (no linearisation): where it
    falls the views prefer the moved place even with nothing else re-fitted.

    A move changes only the blocks between the moved atoms and the rest, so each re-fit is solved
    through the set's inverse information: the atoms left in place through the inverse of their
    own information (the whole inverse with the moved atoms' rows taken out, a Schur complement
    of ``5 |G|`` rows), the moved ones through a system of their own ``5 |G|`` parameters.  On the
    6,679-atom Au particle (21 neighbours a set) this costs half of solving each (5k, 5k)
    system whole, and agrees with it to 1e-9 of the profile's scale (tests).

    ``table``: a :class:`MovedBlocks` that holds the batch's blocks of moved atoms (the host's
    way: each block read once); without it they are read here, on ``info``'s device (a GPU's way:
    reading a block again costs it less than looking it up on the host)."""
    b, k = local.shape
    m = len(offsets)
    dev = info.device
    on = dict(dtype=torch.float64, device=dev)
    column = _columns(local, positions, offsets, axis, hard_core_A, dev)  # (B, M, k)
    g = int(column.sum(axis=2).max())
    order = np.argsort(~column, axis=2, kind="stable")[..., :g]  # the moved first: the atom, then its column
    valid_np = np.take_along_axis(column, order, axis=2)  # (B, M, g): slots a short column leaves empty are False
    bi, mi, ai = np.nonzero(valid_np)
    ii = order[bi, mi, ai]
    # each moved atom at its new place against every atom of its set at its old one: (B, M, g, k, 5, 5)
    cross = torch.zeros((b, m, g, k, 5, 5), **on)
    if table is not None:
        cross[bi, mi, ai] = torch.as_tensor(table.blocks(local[bi, ii], mi, local[bi]), **on)
    elif len(bi):  # read here, on the information's device
        cross[bi, mi, ai] = moved_blocks_here(
            local, bi, mi, ii, positions, sigmas, amps, axes, pixel_size_A, offsets, axis, dev, sight
        )
    gi = torch.as_tensor(order, device=dev)  # (B, M, g) the moved atoms' slots in the set
    valid = torch.as_tensor(valid_np, device=dev)
    is_moved = torch.as_tensor(column, device=dev)  # (B, M, k)
    bb = torch.arange(b, device=dev)[:, None, None]
    mm = torch.arange(m, device=dev)[None, :, None]
    blocks = info.reshape(b, k, 5, k, 5).permute(0, 1, 3, 2, 4)  # [i, j]: rows i's parameters
    local_on = torch.as_tensor(local, device=dev)
    q = torch.as_tensor(amps[local], **on)  # (B, k)
    qg = q[bb, gi] * valid  # (B, M, g) the moved atoms' masses, zero in the empty slots
    pull_now = scores[local_on].sum(dim=2)  # (B, k, 5): J^T r at the fit
    pull_now_g = pull_now[bb, gi]  # (B, M, g, 5)
    pull_moved_g = moved[mm, local_on[bb, gi]]  # (B, M, g, 5): at the moved places
    blocks_gg = blocks[bb[..., None], gi[..., :, None], gi[..., None, :]]  # (B, M, g, g, 5, 5)
    cross_gg = cross[bb[..., None], mm[..., None], torch.arange(g, device=dev)[:, None], gi[..., None, :]]
    # -2 <r, dg> + |dg|^2, dg = sum over the moved of (g_i' - g_i)
    rd = (qg * (pull_moved_g[..., 4] - pull_now_g[..., 4])).sum(-1)
    c44 = cross_gg[..., 4, 4]
    dd = torch.einsum("bma,bmc,bmac->bm", qg, qg, 2 * blocks_gg[..., 4, 4] - c44 - c44.transpose(2, 3))
    frozen = -2 * rd + dd
    # the pull at the moved places, <r - dg, dg_j/dp>: atom j moved, or still at its place
    on_moved = torch.einsum("bmc,bmacp->bmap", qg, blocks_gg[..., :, 4] - cross_gg[..., :, 4])
    towards = blocks[..., :, 4].transpose(1, 2)  # (B, i, j, 5): [i, j, p] = <dg_j/dp, g_i / q_i>
    on_still = torch.einsum("bma,bmajp->bmjp", qg, cross[..., 4, :] - towards[bb, gi])
    pull_g = (pull_moved_g - on_moved).reshape(b, m, 5 * g)
    still = ~is_moved[..., None]
    pull_rest = torch.where(still, pull_now[:, None] - on_still, 0.0).reshape(b, m, 5 * k)
    # the still atoms' coupling to the moved ones at the moved places
    coupling = torch.where(still[..., None, None], cross.permute(0, 1, 3, 5, 2, 4), 0.0).reshape(b, m, 5 * k, 5 * g)
    # the still atoms solved through the inverse information with the moved atoms' rows taken out
    if covariance is None:
        covariance = spd_inverse(info if prior is None else with_prior(info, prior))
    cov = 0.5 * (covariance + covariance.transpose(1, 2))
    rhs = torch.cat([pull_rest[..., None], coupling], dim=-1)  # (B, M, 5k, 1 + 5g)
    c = rhs.shape[-1]
    # the atom itself moves at every offset: its rows are taken out once for all of them, the rest
    # of its column (slots 1.. of the moved) offset by offset
    rest = cov - cov[:, :, :5] @ spd_solve(cov[:, :5, :5], cov[:, :5, :])
    rest = 0.5 * (rest + rest.transpose(1, 2))
    solved = (rest @ rhs.permute(0, 2, 1, 3).reshape(b, 5 * k, m * c)).reshape(b, 5 * k, m, c).permute(0, 2, 1, 3)
    if g > 1:
        rows = (5 * gi[..., 1:, None] + torch.arange(5, device=dev)).reshape(b, m, 5 * (g - 1))  # their parameters
        row_valid = valid[..., 1:, None].expand(b, m, g - 1, 5).reshape(b, m, 5 * (g - 1))
        solved = solved - _taken_out(rest, rows, row_valid, rhs)
    own = blocks_gg.permute(0, 1, 2, 4, 3, 5).reshape(b, m, 5 * g, 5 * g)  # the moved atoms among themselves
    if prior is not None:  # the population's on the moved atoms' widths and amplitudes
        moved_prior = (prior[bb, gi] * valid[..., None, None]).reshape(b * m, g, 2, 2)
        own = with_prior(own.reshape(b * m, 5 * g, 5 * g), moved_prior).reshape(b, m, 5 * g, 5 * g)
    # positions turned to two directions across the axis and the axis; each moved atom's place
    # along the axis held (and every parameter of an empty slot), its row and column cut out
    basis = torch.as_tensor(np.linalg.qr(np.c_[axis, np.eye(3)])[0][:, [1, 2, 0]].T, **on)
    held = torch.zeros((b, m, g, 5), dtype=torch.bool, device=dev)
    held[..., 2] = True
    held = (held | ~valid[..., None]).reshape(b, m, 5 * g)
    u = _turned_pull(pull_g - (coupling * solved[..., :1]).sum(-2), basis)
    schur = _turned(own - coupling.transpose(2, 3) @ solved[..., 1:], basis)
    u = torch.where(held, 0.0, u)
    system = torch.where(held[..., :, None] | held[..., None, :], 0.0, schur) + torch.diag_embed(held.double())
    moved_fit = (pull_rest * solved[..., 0]).sum(-1) + (u * spd_solve(system, u[..., None])[..., 0]).sum(-1)
    # the fit as it is with the same places held: the information's inverse, turned, with the
    # held rows taken out (a Schur complement of |G| rows)
    cov_t = _turned(cov, basis)  # (B, 5k, 5k)
    t = _turned_pull(pull_now.reshape(b, 5 * k), basis)  # (B, 5k)
    axis_rows = 5 * gi + 2  # (B, M, g)
    columns, corner = _rows_of(cov_t, axis_rows, valid)
    t_held = t[bb, axis_rows] * valid
    w = (cov_t @ t[..., None])[:, None, :, 0] - (columns @ t_held[..., None])[..., 0]  # C z, z: t held rows cut
    w_held = w[bb, mm, axis_rows] * valid
    as_is = (t[:, None] * w).sum(-1) - (t_held * w_held).sum(-1)
    as_is = as_is - (w_held * spd_solve(corner, w_held[..., None])[..., 0]).sum(-1)
    return frozen - moved_fit + as_is, frozen


def moved_blocks_here(
    local, bi, mi, ii, positions, sigmas, amps, axes, pixel_size_A, offsets, axis, device, sight=None
):
    """(R, k, 5, 5) float64 on ``device``: atom ``local[bi, ii]`` moved by ``offsets[mi]`` along
    ``axis`` against every atom of its set ``local[bi]`` (``local`` (B, k); ``bi``, ``mi``, ``ii``
    (R,)), rows the moved atom's parameters (:func:`~.information.pair_blocks`, gathered and read
    on ``device``: a GPU's way, where reading a block again costs less than looking it up,
    :class:`MovedBlocks`; the pairs gathered on its host had taken 3.0 of the 13 s a
    54,000-atom particle's evidence took on an H200)."""
    k = local.shape[1]
    on = dict(dtype=torch.float64, device=device)
    at = lambda a: torch.as_tensor(np.asarray(a), device=device)  # noqa: E731
    near = at(local)
    moved, others = near[at(bi), at(ii)], near[at(bi)].reshape(-1)  # (R,), (R k,)
    place = torch.as_tensor(np.require(positions, np.float64, "W"), **on)
    width, mass = (torch.as_tensor(np.require(a, np.float64, "W"), **on) for a in (sigmas, amps))
    step = torch.as_tensor(np.asarray(offsets, np.float64)[:, None] * np.asarray(axis, np.float64), **on)
    moved_places = place[moved] + step[at(mi)]
    blocks = pair_blocks(
        moved_places.repeat_interleave(k, dim=0),
        place[others],
        width[moved].repeat_interleave(k),
        width[others],
        mass[moved].repeat_interleave(k),
        mass[others],
        *view_planes(axes, device),
        pixel_size_A,
        sight,
    )
    return blocks.reshape(-1, k, 5, 5)


def _taken_out(inverse, rows, row_valid, rhs):
    """(B, M, n, c): what taking the ``rows`` (B, M, r) out of a system changes in its inverse's
    product with ``rhs`` (B, M, n, c), ``inverse`` (B, n, n) the whole system's: the inverse of
    the system without them is ``C - C[:, rows] C[rows, rows]^-1 C[rows, :]`` on the rest (rows
    ``row_valid`` False stand for nothing).  ``rhs`` is zero on the rows taken out."""
    columns, corner = _rows_of(inverse, rows, row_valid)
    return columns @ spd_solve(corner, columns.transpose(2, 3) @ rhs)


def _rows_of(inverse, rows, row_valid):
    """``inverse[:, rows]`` (B, M, n, r) and ``inverse[rows, rows]`` (B, M, r, r) of a symmetric
    ``inverse`` (B, n, n), a row ``row_valid`` False zero (its corner a unit diagonal)."""
    b, m, r = rows.shape
    n = inverse.shape[-1]
    columns = torch.gather(inverse[:, None].expand(b, m, n, n), 3, rows[:, :, None, :].expand(b, m, n, r))
    columns = columns * row_valid[:, :, None, :]
    corner = torch.gather(columns, 2, rows[..., None].expand(b, m, r, r))
    eye = torch.eye(r, dtype=inverse.dtype, device=inverse.device)
    return columns, torch.where(row_valid[..., :, None] & row_valid[..., None, :], corner, eye)


def _turned(system, basis):
    """``system`` (..., 5a, 5a), each atom's position rows and columns turned to ``basis`` (3, 3)."""
    a = system.shape[-1] // 5
    parts = system.reshape(*system.shape[:-2], a, 5, a, 5).clone()
    parts[..., :3, :, :] = torch.einsum("de,...aecf->...adcf", basis, parts[..., :3, :, :])
    parts[..., :3] = torch.einsum("...aecf,df->...aecd", parts[..., :3], basis)
    return parts.reshape(system.shape)


def _turned_pull(pull, basis):
    """``pull`` (..., 5a), each atom's position entries turned to ``basis`` (3, 3)."""
    parts = pull.reshape(*pull.shape[:-1], -1, 5).clone()
    parts[..., :3] = parts[..., :3] @ basis.T
    return parts.reshape(pull.shape)


class MovedBlocks:
    """The information blocks of atoms moved along the depth axis against atoms where they are,
    each read once: ``pair_information`` of atom ``i`` at ``positions[i] + offsets[m] axis`` and
    atom ``j`` at its place, for every (i, m, j) of ``moved`` (R,), ``offset_index`` (R,) and
    ``others`` (R, k) (each moved atom against every atom of its set).  One moved atom meets the
    same atom in the sets of all the atoms of its column: on the Au particle each block is asked for
    2.5 times on average."""

    def __init__(
        self, moved, offset_index, others, positions, sigmas, amps, axes, pixel_size_A, offsets, axis, sight=None
    ):
        self.n, self.m = len(positions), len(offsets)
        others = np.asarray(others).reshape(len(moved), -1)
        keys = unique_keys(self._keys(np.asarray(moved)[:, None], np.asarray(offset_index)[:, None], others))
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
                sight=sight,
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


def moved_blocks_of(
    sets, positions, sigmas, amps, axes, pixel_size_A, offsets, axis, hard_core_A, sight=None
) -> MovedBlocks:
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
    return MovedBlocks(*picked, positions, sigmas, amps, axes, pixel_size_A, offsets, axis, sight)
