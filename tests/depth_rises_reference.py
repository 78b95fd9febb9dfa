"""The depth profile as first written: every (atom, offset) system built whole and solved
whole, (B, M, 5k, 5k).  :func:`gaussian_atoms_method.atoms.depth_profile.depth_rises` solves the
same systems through the set's inverse information; this is its float64 reference in the tests."""

from __future__ import annotations

import numpy as np
import torch

from gaussian_atoms_method.atoms.depth_profile import _columns, moved_blocks_here
from gaussian_atoms_method.atoms.population import with_prior


def depth_rises_reference(
    local, info, scores, moved, offsets, positions, sigmas, amps, axes, pixel_size_A, hard_core_A, axis, table=None,
    prior=None,
) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """:func:`gaussian_atoms_method.atoms.depth_profile.depth_rises` (its arguments and its two
    (B, M) rises) with every moved set's (5k, 5k) system built whole, turned whole and solved whole:
    the moved atoms' blocks against the still ones replaced by the moved blocks, the held places'
    rows and columns cut out, and the fit as it is solved once per distinct held pattern; a
    ``prior`` (B, k, 2, 2) added to every atom's width and amplitude rows of both systems."""
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
        cross[bi, mi, ii] = moved_blocks_here(
            local, bi, mi, ii, positions, sigmas, amps, axes, pixel_size_A, offsets, axis, info.device
        )
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
    system_now = info
    if prior is not None:
        system_now = with_prior(info, prior)
        with_move = with_prior(with_move.reshape(b * m, 5 * k, 5 * k), prior.repeat_interleave(m, dim=0))
        with_move = with_move.reshape(b, m, 5 * k, 5 * k)
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
        turned(system_now)[atom_of],
        turned_pull(pull_now.reshape(b, 5 * k))[atom_of],
        held.reshape(b * m, 5 * k)[torch.as_tensor(once)],
    )[torch.as_tensor(again.ravel(), device=info.device)].reshape(b, m)
    frozen = -2 * rd + dd
    return frozen - refit(turned(with_move), turned_pull(pull), held) + baseline, frozen
