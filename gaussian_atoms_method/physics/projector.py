"""Tomographic projection of isotropic 3D Gaussians onto an orthographic detector.

Physics: the potential of one atom is modelled as ``q exp(-|r - r_a|^2 / (2 sigma^2))``.  Its
line integral along the beam is exactly a 2D Gaussian of the same ``sigma`` with peak
``q * sigma * sqrt(2 pi)``.  A projection is the plain sum of these (no alpha compositing, no
occlusion, no sorting).  The image value at a pixel is the line integral along the ray through
the pixel centre.

Because an isotropic 2D Gaussian is separable, the image of ``N`` atoms is one matrix product
``G_rows^T diag(peak) G_cols`` of two small matrices of 1D Gaussians, ``(H, N) @ (N, W)``: exact,
differentiable by autograd, and runs on any torch device.  (Keep TF32 off on CUDA: it makes this
product about 0.6% wrong.)
"""

from __future__ import annotations

import math

import numpy as np
import torch

SQRT_2PI = math.sqrt(2.0 * math.pi)


def projected_peak(sigmas: torch.Tensor, amplitudes: torch.Tensor) -> torch.Tensor:
    """Peak of the projected 2D Gaussian, ``amplitude * sigma * sqrt(2 pi)``."""
    return amplitudes * sigmas * SQRT_2PI


def gaussian_mass(sigmas: torch.Tensor, amplitudes: torch.Tensor) -> torch.Tensor:
    """Integral of the 3D Gaussian over all space, ``amplitude * (2 pi sigma^2)^(3/2)``."""
    return amplitudes * (2.0 * math.pi * sigmas**2) ** 1.5


def typical_mass(masses: torch.Tensor) -> float:
    """Mass-weighted median of ``masses`` (any shape): half of the total mass sits in entries
    at least this heavy, so many faint entries do not pull it down.  0 when there are none."""
    if masses.numel() == 0:
        return 0.0
    mass, _ = torch.sort(masses.flatten())
    cumulative = torch.cumsum(mass, 0)
    return float(mass[torch.searchsorted(cumulative, 0.5 * cumulative[-1]).clamp_max(len(mass) - 1)])


def project_gaussians(
    means: torch.Tensor,
    sigmas: torch.Tensor,
    amplitudes: torch.Tensor,
    detector_axes: torch.Tensor,
    row_coords: torch.Tensor,
    col_coords: torch.Tensor,
) -> torch.Tensor:
    """Line-integral projections of isotropic Gaussians.

    All lengths are in one unit (Å, or the normalised units used in training).

    Parameters
    ----------
    means : (N, 3) tensor
        Gaussian centres in world coordinates.
    sigmas : (N,) tensor
        Standard deviations (> 0).
    amplitudes : (N,) tensor
        3D peak values ``q``.
    detector_axes : (V, 3, 3) or (V, 2, 3) tensor
        Per view, the world directions of the detector rows and columns (and beam, unused);
        see :mod:`gaussian_atoms_method.physics.geometry`.
    row_coords : (H,) tensor
        Coordinates of the pixel centres along the detector rows.
    col_coords : (W,) tensor
        Coordinates of the pixel centres along the detector columns.

    Returns
    -------
    images : (V, H, W) tensor
        Line integrals, in units of amplitude x length.
    """
    if means.ndim != 2 or means.shape[-1] != 3:
        raise ValueError(f"means must have shape (N, 3), got {tuple(means.shape)}")
    n = means.shape[0]
    if sigmas.shape != (n,) or amplitudes.shape != (n,):
        raise ValueError(
            f"sigmas and amplitudes must have shape ({n},), got {tuple(sigmas.shape)} and {tuple(amplitudes.shape)}"
        )
    u, v = _detector_coordinates(detector_axes, means)  # (V, N) each
    rate = -0.5 / sigmas**2  # (N,), negative: the exponent's factor on the (N,) side, not negated per pixel
    peak = projected_peak(sigmas, amplitudes)  # (N,)
    g_rows = torch.exp((row_coords[None, :, None] - u[:, None, :]).square() * rate)  # (V, H, N)
    g_cols = torch.exp((col_coords[None, None, :] - v[:, :, None]).square() * rate[:, None])  # (V, N, W)
    return torch.bmm(g_rows * peak, g_cols)


def _detector_coordinates(detector_axes: torch.Tensor, means: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(V, N) coordinates of every centre along each view's detector rows and columns, one
    matrix product for both (two einsums dispatched 26 operations a step, forward and backward
    alike: host time a GPU step waits on)."""
    return (detector_axes[:, :2, :].reshape(-1, 3) @ means.T).reshape(-1, 2, means.shape[0]).unbind(1)


def _uniform_spacing(coords: torch.Tensor, what: str) -> float:
    if coords.ndim != 1 or len(coords) == 0:
        raise ValueError(f"{what} must be a non-empty 1D tensor, got shape {tuple(coords.shape)}")
    if len(coords) == 1:
        return 1.0
    step = (coords[1:] - coords[:-1]).detach()
    d = float(step[0])
    if d == 0 or not torch.allclose(step, step[0].expand_as(step), rtol=1e-4, atol=0.0):
        raise ValueError(f"{what} must be evenly spaced pixel centres for the tiled projector")
    return d


def _extend(coords: torch.Tensor, length: int, step: float) -> torch.Tensor:
    extra = length - len(coords)
    if extra <= 0:
        return coords
    return torch.cat([coords, coords[-1] + step * torch.arange(1, extra + 1, device=coords.device, dtype=coords.dtype)])


def _check_shapes(means: torch.Tensor, per_gaussian: dict) -> int:
    if means.ndim != 2 or means.shape[-1] != 3:
        raise ValueError(f"means must have shape (N, 3), got {tuple(means.shape)}")
    n = means.shape[0]
    for name, (tensor, tail) in per_gaussian.items():
        if tuple(tensor.shape) != (n,) + tail:
            raise ValueError(f"{name} must have shape {(n,) + tail}, got {tuple(tensor.shape)}")
    return n


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
    CPU, where the indices fit 16 bits, numpy's radix sort of them (the same order): the Au
    series' 24,650 (Gaussian, tile) pairs of a view in 0.14 ms, against 1.4 ms for torch's sort
    on the 2-core CPU."""
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


def _assemble(
    blocks: torch.Tensor, used: torch.Tensor, n_views: int, grid, tile: int, height: int, width: int
) -> torch.Tensor:
    """(T, tile, tile) blocks of the non-empty tiles -> (V, H, W) images (zeros elsewhere)."""
    tiles_r, tiles_c = grid
    padded = blocks.new_zeros(n_views * tiles_r * tiles_c, tile, tile).index_copy(0, used, blocks)
    padded = padded.reshape(n_views, tiles_r, tiles_c, tile, tile).permute(0, 1, 3, 2, 4)
    return padded.reshape(n_views, tiles_r * tile, tiles_c * tile)[:, :height, :width]


def _pad_gather(values: torch.Tensor, index: torch.Tensor, pad: float = 0.0) -> torch.Tensor:
    """``values`` flattened to (V*N, ...) plus one sentinel row of ``pad``, gathered at ``index``."""
    flat = values.reshape((-1,) + tuple(values.shape[2:])) if values.dim() > 1 else values
    sentinel = torch.full((1,) + tuple(flat.shape[1:]), pad, dtype=flat.dtype, device=flat.device)
    return torch.cat([flat, sentinel])[index]


def project_gaussians_tiled(
    means: torch.Tensor,
    sigmas: torch.Tensor,
    amplitudes: torch.Tensor,
    detector_axes: torch.Tensor,
    row_coords: torch.Tensor,
    col_coords: torch.Tensor,
    tile: int = 32,
    cutoff_sigmas: float = 5.5,
    pairing=None,
) -> torch.Tensor:
    """The same projections as :func:`project_gaussians`, evaluating each Gaussian only on the
    detector tiles within ``cutoff_sigmas`` of its centre (``pairing``: the function listing
    (Gaussian, tile) pairs, :func:`tile_pairs` by default).

    A dense product costs ``N * H * W`` multiply-adds per view although an atom covers a few
    hundred pixels.  Here the detector is cut into ``tile x tile`` squares; every (Gaussian,
    tile) pair where the Gaussian's window reaches the tile is listed (:func:`tile_pairs`),
    tiles with nothing in them are skipped, and each non-empty tile is the small separable
    product of the Gaussians that reach it (padded to the fullest tile's count, one batched
    matmul).  The tails cut at ``cutoff_sigmas`` weigh ``exp(-cutoff^2 / 2)`` of a peak (2.7e-7
    at 5.5): below float32 resolution.  Parameters and result as :func:`project_gaussians`; the
    pixel coordinates must be evenly spaced.
    """
    n = _check_shapes(means, {"sigmas": (sigmas, ()), "amplitudes": (amplitudes, ())})
    dr, dc = _uniform_spacing(row_coords, "row_coords"), _uniform_spacing(col_coords, "col_coords")
    n_views, h, w = detector_axes.shape[0], len(row_coords), len(col_coords)
    dt = means.dtype
    if n == 0:
        return means.new_zeros(n_views, h, w)
    u, v = _detector_coordinates(detector_axes.to(dt), means)  # (V, N) along rows, columns
    radius = (cutoff_sigmas * sigmas.detach())[None, :]
    used, index, rows_px, cols_px, grid = (pairing or tile_pairs)(
        (u.detach() - row_coords[0]) / dr,
        (v.detach() - col_coords[0]) / dc,
        radius / abs(dr),
        radius / abs(dc),
        h,
        w,
        tile,
    )
    if len(used) == 0:
        return means.new_zeros(n_views, h, w)
    return _separable_tiles(
        u, v, sigmas, amplitudes, used, index, rows_px, cols_px, grid, tile, row_coords, col_coords, dr, dc, h, w
    )


TILE_GROUPS = 4
"""The tiles are evaluated in this many groups of similar occupancy (equal counts of tiles,
fullest first), each padded to its own fullest tile rather than all to the fullest of all: on
the Au series (6,679 atoms, 271 x 271 pixels, tiles of 32) the tiles hold 1-730 Gaussians, and
one padding computed 2.3 times the needed exponentials and products, four groups 1.29 times."""


def _separable_tiles(
    u, v, sigmas, amplitudes, used, index, rows_px, cols_px, grid, tile, row_coords, col_coords, dr, dc, h, w
):
    """Evaluate isotropic Gaussians on the listed tiles (see :func:`tile_pairs`) and assemble,
    in :data:`TILE_GROUPS` groups of tiles of similar occupancy (each tile's list holds its
    Gaussians first, then the sentinel)."""
    n_views, n = u.shape
    dt = u.dtype

    def per_view(x):
        return x[None, :].expand(n_views, n)

    # the exponent's (negative) factor
    peak, rate = (
        per_view(projected_peak(sigmas, amplitudes)),
        per_view(-0.5 / sigmas**2),
    )
    # (T, tile) pixel coordinates: the given ones, extrapolated past the last tile's edge.
    row_all = _extend(row_coords.to(dt), grid[0] * tile, dr)[rows_px]
    col_all = _extend(col_coords.to(dt), grid[1] * tile, dc)[cols_px]
    held = (index < n_views * n).sum(dim=1)
    groups = [
        g
        for g in torch.tensor_split(torch.argsort(held, descending=True, stable=True), min(TILE_GROUPS, len(held)))
        if len(g)
    ]
    fullest = held[torch.stack([g[0] for g in groups])].tolist()  # one read of the device for all groups
    blocks = []
    for group, k in zip(groups, fullest):
        part = index[group, : max(int(k), 1)]
        U, Vc = _pad_gather(u, part), _pad_gather(v, part)  # (T_g, K_g)
        P, S = _pad_gather(peak, part), _pad_gather(rate, part, pad=-1.0)
        blocks.append(tile_blocks(U, Vc, P, S, row_all[group], col_all[group]))
    return _assemble(torch.cat(blocks), used[torch.cat(groups)], n_views, grid, tile, h, w)


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
edge is 17 widths from an Au atom's centre, across a 32-pixel tile), and torch's CPU exponential
takes 10 times as long on inputs that underflow (2.3 against 0.22 ms for 410,000 values)."""


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
        # d(blocks)/d(e_rows P) = grad @ g_cols^T; times e_rows: the gradient of the rows' exponent over P
        rows = torch.bmm(grad, g_cols.transpose(1, 2)).mul_(e_rows)  # (T, tile, K)
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
    of one view of the Au series' 6,679 atoms (0.67 Å, 271 x 271 pixels of 0.25 Å) on the 2-core
    CPU, alternated in one process, 41-43 ms with the reference, 20-24 ms with this."""
    return _TileBlocks.apply(U, Vc, P, S, row_c, col_c)


@torch.no_grad()
def gsplat_tile_pairs(u_px, v_px, radius_r_px, radius_c_px, height: int, width: int, tile: int):
    """:func:`tile_pairs` computed by stock gsplat (CUDA only): its orthographic projection of
    means and covariances gives each Gaussian's pixel position and radius, its tile
    intersection the sorted (tile, Gaussian) list.  gsplat's radius is 3 standard deviations of
    the covariance it is given, so it is given the covariance of ``radius_px / 3`` to cut the
    windows where ours are cut.  Same returns as :func:`tile_pairs`."""
    from gsplat.cuda._wrapper import fully_fused_projection, isect_offset_encode, isect_tiles

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


def project_gaussians_gsplat(
    means: torch.Tensor,
    sigmas: torch.Tensor,
    amplitudes: torch.Tensor,
    detector_axes: torch.Tensor,
    row_coords: torch.Tensor,
    col_coords: torch.Tensor,
    tile: int = 16,
    cutoff_sigmas: float = 5.5,
) -> torch.Tensor:
    """:func:`project_gaussians_tiled` with the tile lists made by stock gsplat 1.4.0 on CUDA
    (:func:`gsplat_tile_pairs`).  gsplat's rasteriser alpha-composites, the wrong physics for a
    line integral, so the accumulation stays additive and in torch; gradients flow through the
    torch part (gsplat only decides which tiles each Gaussian reaches)."""
    if means.device.type != "cuda":
        raise ValueError("the gsplat projector needs a CUDA device; use projector 'tiled' on CPU")
    return project_gaussians_tiled(
        means, sigmas, amplitudes, detector_axes, row_coords, col_coords, tile, cutoff_sigmas, gsplat_tile_pairs
    )


def covariances_from_scales_quats(log_scales: torch.Tensor, quats: torch.Tensor) -> torch.Tensor:
    """(N, 3, 3) covariances ``R diag(s^2) R^T`` from (N, 3) log standard deviations and (N, 4)
    quaternions ``(w, x, y, z)`` (normalised here)."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    rot = torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(-1, 3, 3)
    return rot @ torch.diag_embed(torch.exp(2 * log_scales)) @ rot.transpose(-1, -2)


def project_anisotropic_gaussians(
    means: torch.Tensor,
    covariances: torch.Tensor,
    amplitudes: torch.Tensor,
    detector_axes: torch.Tensor,
    row_coords: torch.Tensor,
    col_coords: torch.Tensor,
    tile: int = 16,
    cutoff_sigmas: float = 5.5,
) -> torch.Tensor:
    """Line-integral projections of general 3D Gaussians ``q exp(-r^T C^-1 r / 2)`` (the
    ablation without the isotropy prior).

    Along a beam ``b`` (unit vector orthogonal to the detector axes ``A``, 2x3), the integral is
    the 2D Gaussian of covariance ``A C A^T`` with peak ``q sqrt(2 pi det C / det(A C A^T))``
    (for ``C = sigma^2 I`` this is ``q sigma sqrt(2 pi)``).  It is not separable, so each tile
    evaluates its Gaussians on all its pixels; windows are the ellipse's bounding box at
    ``cutoff_sigmas``.

    Parameters
    ----------
    means : (N, 3); covariances : (N, 3, 3) symmetric positive definite; amplitudes : (N,)
    detector_axes, row_coords, col_coords : as :func:`project_gaussians` (evenly spaced)

    Returns
    -------
    images : (V, H, W) tensor
    """
    n = _check_shapes(means, {"covariances": (covariances, (3, 3)), "amplitudes": (amplitudes, ())})
    dr, dc = _uniform_spacing(row_coords, "row_coords"), _uniform_spacing(col_coords, "col_coords")
    n_views, h, w = detector_axes.shape[0], len(row_coords), len(col_coords)
    dt = means.dtype
    if n == 0:
        return means.new_zeros(n_views, h, w)
    axes2 = detector_axes[:, :2, :].to(dt)  # (V, 2, 3)
    centres = torch.einsum("vkc,nc->vnk", axes2, means)  # (V, N, 2)
    cov2 = torch.einsum("vkc,ncd,vld->vnkl", axes2, covariances, axes2)  # (V, N, 2, 2)
    det2 = cov2[..., 0, 0] * cov2[..., 1, 1] - cov2[..., 0, 1] ** 2
    peak = amplitudes[None, :] * torch.sqrt(2 * math.pi * torch.linalg.det(covariances)[None, :] / det2)
    inv = torch.stack([cov2[..., 1, 1], -cov2[..., 0, 1], cov2[..., 0, 0]], dim=-1) / det2[..., None]  # (V, N, 3)
    with torch.no_grad():
        rad_r = cutoff_sigmas * cov2[..., 0, 0].sqrt() / abs(dr)
        rad_c = cutoff_sigmas * cov2[..., 1, 1].sqrt() / abs(dc)
    used, index, rows_px, cols_px, grid = tile_pairs(
        (centres[..., 0].detach() - row_coords[0]) / dr,
        (centres[..., 1].detach() - col_coords[0]) / dc,
        rad_r,
        rad_c,
        h,
        w,
        tile,
    )
    if len(used) == 0:
        return means.new_zeros(n_views, h, w)
    U, Vc, P = _pad_gather(centres[..., 0], index), _pad_gather(centres[..., 1], index), _pad_gather(peak, index)
    inv_k = _pad_gather(inv, index, pad=1.0)  # (T, K, 3)
    row_c = _extend(row_coords.to(dt), grid[0] * tile, dr)[rows_px]
    col_c = _extend(col_coords.to(dt), grid[1] * tile, dc)[cols_px]
    du = row_c[:, None, :, None] - U[:, :, None, None]  # (T, K, tile, 1)
    dv = col_c[:, None, None, :] - Vc[:, :, None, None]  # (T, K, 1, tile)
    a, b, c = (inv_k[..., j, None, None] for j in range(3))
    blocks = (P[:, :, None, None] * torch.exp(-0.5 * (a * du**2 + 2 * b * du * dv + c * dv**2))).sum(1)
    return _assemble(blocks, used, n_views, grid, tile, h, w)
