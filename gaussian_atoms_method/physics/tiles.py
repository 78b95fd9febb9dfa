"""The tiles of the tiled projectors: which Gaussians reach which detector tiles (ours, or
stock gsplat's on CUDA), and the batched evaluation of a tile's Gaussians with a hand-written
backward (:func:`tile_blocks`; :func:`tile_blocks_reference` is the plain torch it equals)."""

from __future__ import annotations

import numpy as np
import torch


def uniform_spacing(coords: torch.Tensor, what: str) -> float:
    if coords.ndim != 1 or len(coords) == 0:
        raise ValueError(f"{what} must be a non-empty 1D tensor, got shape {tuple(coords.shape)}")
    if len(coords) == 1:
        return 1.0
    step = (coords[1:] - coords[:-1]).detach()
    d = float(step[0])
    if d == 0 or not torch.allclose(step, step[0].expand_as(step), rtol=1e-4, atol=0.0):
        raise ValueError(f"{what} must be evenly spaced pixel centres for the tiled projector")
    return d


def extended_coordinates(coords: torch.Tensor, length: int, step: float) -> torch.Tensor:
    extra = length - len(coords)
    if extra <= 0:
        return coords
    return torch.cat([coords, coords[-1] + step * torch.arange(1, extra + 1, device=coords.device, dtype=coords.dtype)])


@torch.no_grad()
def tile_pairs(u_px, v_px, radius_r_px, radius_c_px, height: int, width: int, tile: int):
    """List the (Gaussian, tile) pairs where a Gaussian's window reaches a detector tile.

    Parameters
    ----------
    u_px, v_px : (V, N) tensors
        Fractional pixel indices (row, column) of each Gaussian's centre in each view.
    radius_r_px, radius_c_px : (V, N) or (1, N) tensors
        Half-widths of each window along rows and columns, pixels.
    height, width, tile : int
        Detector size and tile side, pixels.

    Returns
    -------
    used : (T,) long, flat index ``(view * tiles_r + tile_row) * tiles_c + tile_col`` of every
        non-empty tile (empty tiles are skipped);
    index : (T, K) long, flat ``view * N + gaussian`` of each tile's Gaussians, padded with
        ``V * N`` (a sentinel the callers map to a zero-weight Gaussian);
    rows_px, cols_px : (T, tile) long, pixel indices each tile covers (may run past the edge);
    grid : (tiles_r, tiles_c).
    """
    n_views, n = u_px.shape
    dev = u_px.device
    tiles_r, tiles_c = -(-height // tile), -(-width // tile)
    lo_r, hi_r = torch.floor((u_px - radius_r_px) / tile), torch.floor((u_px + radius_r_px) / tile)
    lo_c, hi_c = torch.floor((v_px - radius_c_px) / tile), torch.floor((v_px + radius_c_px) / tile)
    seen = (hi_r >= 0) & (lo_r < tiles_r) & (hi_c >= 0) & (lo_c < tiles_c)
    lo_r, hi_r = lo_r.clamp(0, tiles_r - 1).long(), hi_r.clamp(0, tiles_r - 1).long()
    lo_c, hi_c = lo_c.clamp(0, tiles_c - 1).long(), hi_c.clamp(0, tiles_c - 1).long()
    n_c = hi_c - lo_c + 1
    counts = torch.where(seen, (hi_r - lo_r + 1) * n_c, torch.zeros_like(n_c)).flatten()  # (V*N,)
    empty = torch.zeros(0, dtype=torch.long, device=dev)
    if int(counts.sum()) == 0:
        return empty, empty.reshape(0, 1), empty.reshape(0, tile), empty.reshape(0, tile), (tiles_r, tiles_c)
    pair_src = torch.repeat_interleave(torch.arange(n_views * n, device=dev), counts)
    k = torch.arange(len(pair_src), device=dev) - (torch.cumsum(counts, 0) - counts)[pair_src]
    n_c_p = n_c.flatten()[pair_src]
    t_r = lo_r.flatten()[pair_src] + k // n_c_p
    t_c = lo_c.flatten()[pair_src] + k % n_c_p
    tile_id = ((pair_src // n) * tiles_r + t_r) * tiles_c + t_c
    order = tile_order(tile_id, n_views * tiles_r * tiles_c)
    tile_id, pair_src = tile_id[order], pair_src[order]
    used, per_tile = torch.unique_consecutive(tile_id, return_counts=True)
    return _tile_lists(
        used, per_tile, torch.cumsum(per_tile, 0) - per_tile, pair_src, n_views * n, (tiles_r, tiles_c), tile
    )


def tile_order(tile_id: torch.Tensor, n_tiles: int) -> torch.Tensor:
    """``torch.argsort(tile_id, stable=True)`` for (P,) tile indices below ``n_tiles``.  On the
    CPU, where the indices fit 16 bits, numpy's radix sort of them (the same order, in linear
    time)."""
    if tile_id.device.type == "cpu" and n_tiles <= np.iinfo(np.int16).max:
        return torch.from_numpy(tile_id.numpy().astype(np.int16).argsort(kind="stable"))
    return torch.argsort(tile_id, stable=True)


def _tile_lists(used, per_tile, starts, pair_src, sentinel: int, grid, tile: int):
    """Padded per-tile index lists from pairs sorted by tile: tile ``used[t]`` holds
    ``pair_src[starts[t] : starts[t] + per_tile[t]]``."""
    dev = used.device
    tiles_r, tiles_c = grid
    slot = torch.arange(len(pair_src), device=dev) - torch.repeat_interleave(starts, per_tile)
    row_of_pair = torch.repeat_interleave(torch.arange(len(used), device=dev), per_tile)
    index = torch.full((len(used), int(per_tile.max())), sentinel, device=dev, dtype=torch.long)
    index[row_of_pair, slot] = pair_src
    offsets = torch.arange(tile, device=dev)
    rows_px = ((used // tiles_c) % tiles_r)[:, None] * tile + offsets
    cols_px = (used % tiles_c)[:, None] * tile + offsets
    return used, index, rows_px, cols_px, grid


def assemble_tiles(
    blocks: torch.Tensor, used: torch.Tensor, n_views: int, grid, tile: int, height: int, width: int
) -> torch.Tensor:
    """(T, tile, tile) blocks of the non-empty tiles -> (V, H, W) images (zeros elsewhere)."""
    tiles_r, tiles_c = grid
    padded = blocks.new_zeros(n_views * tiles_r * tiles_c, tile, tile).index_copy(0, used, blocks)
    padded = padded.reshape(n_views, tiles_r, tiles_c, tile, tile).permute(0, 1, 3, 2, 4)
    return padded.reshape(n_views, tiles_r * tile, tiles_c * tile)[:, :height, :width]


def pad_gather(values: torch.Tensor, index: torch.Tensor, pad: float = 0.0) -> torch.Tensor:
    """``values`` flattened to (V*N, ...) plus one sentinel row of ``pad``, gathered at ``index``.

    On the CPU through ``index_select``, whose gradient sums each Gaussian's tiles in one order
    (``index_add_``); an indexing's gradient (``index_put_`` accumulating) adds them from both
    threads at once, in an order that changes from run to run: three CPU runs of one 54,000-atom
    series wrote 54,009, 54,020 and 54,012 atoms.  On a GPU the indexing stays (its gradient
    sorts the indices; ``index_add_`` there adds atomically)."""
    flat = values.reshape((-1,) + tuple(values.shape[2:])) if values.dim() > 1 else values
    sentinel = torch.full((1,) + tuple(flat.shape[1:]), pad, dtype=flat.dtype, device=flat.device)
    padded = torch.cat([flat, sentinel])
    if padded.device.type != "cpu":
        return padded[index]
    return padded.index_select(0, index.reshape(-1)).reshape(tuple(index.shape) + tuple(flat.shape[1:]))


def tile_blocks_reference(U, Vc, P, S, row_c, col_c):
    """The (T, tile, tile) images of the tiles' Gaussians: tile ``t`` holds Gaussians of row
    and column centres ``U[t]``, ``Vc[t]`` (T, K), peaks ``P[t]`` and exponent factors ``S[t]``
    (``-1 / (2 sigma^2)``) on the pixel coordinates ``row_c[t]``, ``col_c[t]`` (T, tile): one
    separable product per tile, differentiated by autograd (the tests' reference for
    :func:`tile_blocks`)."""
    g_rows = torch.exp((row_c[:, :, None] - U[:, None, :]).square() * S[:, None, :]) * P[:, None, :]  # (T, tile, K)
    g_cols = torch.exp((col_c[:, None, :] - Vc[:, :, None]).square() * S[:, :, None])  # (T, K, tile)
    return torch.bmm(g_rows, g_cols)


EXPONENT_FLOOR = -87.0
"""The tiles' exponents are raised to this before the exponential: ``exp(-87)``, 1.6e-38, is
float32's smallest normal number, and a term that small is nothing beside any peak.  A tile holds
the Gaussians whose windows reach it, so most of its terms lie far below that (a window's far
edge is 11 widths from an Au atom's centre, across a 16-pixel tile), and torch's CPU exponential
takes about ten times as long on inputs that underflow."""


class _TileBlocks(torch.autograd.Function):
    """:func:`tile_blocks_reference` with its backward written out: the gradients of the
    exponents ``S d^2`` reduced over each tile's pixels in a few passes over the (T, tile, K)
    products, where autograd keeps and walks a node for every elementwise step (the exponent's
    difference, square, factor, exponential and the peak's product, on both axes)."""

    @staticmethod
    def forward(ctx, U, Vc, P, S, row_c, col_c):
        # (T, tile, K)
        e_rows = (row_c[:, :, None] - U[:, None, :]).square_().mul_(S[:, None, :]).clamp_(min=EXPONENT_FLOOR).exp_()
        # (T, K, tile)
        g_cols = (col_c[:, None, :] - Vc[:, :, None]).square_().mul_(S[:, :, None]).clamp_(min=EXPONENT_FLOOR).exp_()
        ctx.save_for_backward(U, Vc, P, S, row_c, col_c, e_rows, g_cols)
        return torch.bmm(e_rows * P[:, None, :], g_cols)

    @staticmethod
    def backward(ctx, grad):
        U, Vc, P, S, row_c, col_c, e_rows, g_cols = ctx.saved_tensors
        grad = grad.contiguous()
        # d(blocks)/d(e_rows P) = grad @ g_cols^T; times e_rows: the gradient of the rows' exponent over P.
        # On the CPU formed as (g_cols @ grad^T)^T: the same products to the bit, where MKL's batched
        # product with the K-long side last took 5x as long (6.9 against 1.3 ms at T 18, K 806)
        if grad.device.type == "cpu":
            rows = torch.bmm(g_cols, grad.transpose(1, 2)).transpose(1, 2).contiguous()
        else:
            rows = torch.bmm(grad, g_cols.transpose(1, 2))
        rows.mul_(e_rows)  # (T, tile, K)
        # d(blocks)/d(g_cols) = (e_rows P)^T @ grad; times g_cols: the columns' exponent's over P
        cols = torch.bmm(e_rows.transpose(1, 2), grad).mul_(g_cols)  # (T, K, tile)
        grad_P = rows.sum(dim=1)  # (T, K)
        d_rows, d_cols = row_c[:, :, None] - U[:, None, :], col_c[:, None, :] - Vc[:, :, None]  # d = pixel - centre
        rows.mul_(d_rows)
        cols.mul_(d_cols)
        slope = 2.0 * S * P  # the exponent S d^2 changes by 2 S d per unit of d; P from "over P"
        # the pixels' coordinates (a view's shift moves them): + slope d, summed over the Gaussians
        grad_rows = (rows * slope[:, None, :]).sum(dim=2) if ctx.needs_input_grad[4] else None
        grad_cols = (cols * slope[:, :, None]).sum(dim=1) if ctx.needs_input_grad[5] else None
        first_rows, first_cols = rows.sum(dim=1), cols.sum(dim=2)
        second = rows.mul_(d_rows).sum(dim=1) + cols.mul_(d_cols).sum(dim=2)  # ... d^2
        return first_rows.mul_(-slope), first_cols.mul_(-slope), grad_P, second.mul_(P), grad_rows, grad_cols


def tile_blocks(U, Vc, P, S, row_c, col_c):
    """:func:`tile_blocks_reference`, with a hand-written backward (:class:`_TileBlocks`) and
    the exponents floored (:data:`EXPONENT_FLOOR`): the tiled projector's forward and backward
    in about half the reference's time on a CPU."""
    return _TileBlocks.apply(U, Vc, P, S, row_c, col_c)


@torch.no_grad()
def gsplat_tile_pairs(u_px, v_px, radius_r_px, radius_c_px, height: int, width: int, tile: int):
    """:func:`tile_pairs` computed by stock gsplat (CUDA only): its orthographic projection of
    means and covariances gives each Gaussian's pixel position and radius, its tile
    intersection the sorted (tile, Gaussian) list.  gsplat's radius is 3 standard deviations of
    the covariance it is given, so it is given the covariance of ``radius_px / 3`` to cut the
    windows where ours are cut.  Same returns as :func:`tile_pairs`."""
    from gsplat import fully_fused_projection, isect_offset_encode, isect_tiles

    n_views, n = u_px.shape
    dev = u_px.device
    tiles_r, tiles_c = -(-height // tile), -(-width // tile)
    # One camera per view looking at points already in pixel units: world (col, row, depth=1).
    # (V, N, 3), gsplat pixel centres at +0.5
    pts = torch.stack([v_px + 0.5, u_px + 0.5, torch.ones_like(u_px)], dim=-1)
    radius = torch.maximum(radius_r_px, radius_c_px).expand(n_views, n)
    means2d_all, radii_all = [], []
    for view in range(n_views):  # gsplat projects all Gaussians into all cameras: one view at a time
        covars = torch.zeros(n, 6, device=dev, dtype=torch.float32)
        var = (radius[view] / 3.0) ** 2
        covars[:, 0], covars[:, 3], covars[:, 5] = var, var, var
        radii, means2d, _, _, _ = fully_fused_projection(
            pts[view].float().contiguous(),
            covars,
            None,
            None,
            torch.eye(4, device=dev)[None],
            torch.eye(3, device=dev)[None],
            width,
            height,
            eps2d=0.0,
            near_plane=1e-3,
            camera_model="ortho",
        )
        radii = radii if radii.dim() == 2 else radii.amax(-1)  # newer gsplat returns (C, N, 2)
        means2d_all.append(means2d)
        radii_all.append(radii)
    means2d, radii = torch.cat(means2d_all), torch.cat(radii_all)
    depths = torch.ones_like(means2d[..., 0])
    _, isect_ids, flatten_ids = isect_tiles(means2d, radii, depths, tile, tiles_c, tiles_r, sort=True)
    offsets = isect_offset_encode(isect_ids, n_views, tiles_c, tiles_r).flatten().long()
    total = len(flatten_ids)
    counts = torch.diff(torch.cat([offsets, torch.tensor([total], device=dev)]))
    used = torch.nonzero(counts > 0).flatten()
    empty = torch.zeros(0, dtype=torch.long, device=dev)
    if len(used) == 0:
        return empty, empty.reshape(0, 1), empty.reshape(0, tile), empty.reshape(0, tile), (tiles_r, tiles_c)
    return _tile_lists(used, counts[used], offsets[used], flatten_ids.long(), n_views * n, (tiles_r, tiles_c), tile)
