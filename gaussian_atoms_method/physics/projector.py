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

import torch

from gaussian_atoms_method.physics.tiles import (
    assemble_tiles,
    extended_coordinates,
    gsplat_tile_pairs,
    pad_gather,
    tile_blocks,
    tile_pairs,
    uniform_spacing,
)

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


def _check_shapes(means: torch.Tensor, per_gaussian: dict) -> int:
    if means.ndim != 2 or means.shape[-1] != 3:
        raise ValueError(f"means must have shape (N, 3), got {tuple(means.shape)}")
    n = means.shape[0]
    for name, (tensor, tail) in per_gaussian.items():
        if tuple(tensor.shape) != (n,) + tail:
            raise ValueError(f"{name} must have shape {(n,) + tail}, got {tuple(tensor.shape)}")
    return n


def project_gaussians_tiled(
    means: torch.Tensor,
    sigmas: torch.Tensor,
    amplitudes: torch.Tensor,
    detector_axes: torch.Tensor,
    row_coords: torch.Tensor,
    col_coords: torch.Tensor,
    tile: int = 16,
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

    A tile's product costs ``tile^2`` per Gaussian that reaches it, and a Gaussian reaches a tile
    from ``cutoff_sigmas`` widths beyond its edge: per pixel the cost grows as ``(tile + 2 R)^2``
    with ``R`` the window's reach, so a smaller tile costs less until the batched products grow
    too small.  ``tile`` 16 (the forward and backward of one view of 6,679 Gaussians on 271 x 271
    pixels, this 2-core CPU): 18 / 22 / 33 / 59 ms against 32's 40 / 36 / 45 / 62 ms at widths of
    1.2 / 1.8 / 2.8 / 4 pixels (8 and 12 were slower at the wider ones).
    """
    n = _check_shapes(means, {"sigmas": (sigmas, ()), "amplitudes": (amplitudes, ())})
    dr, dc = uniform_spacing(row_coords, "row_coords"), uniform_spacing(col_coords, "col_coords")
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
fullest first), each padded to its own fullest tile rather than all to the fullest of all: a
particle's tiles hold from one Gaussian to hundreds, and one padding for all computes about
twice the needed exponentials and products."""


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
    row_all = extended_coordinates(row_coords.to(dt), grid[0] * tile, dr)[rows_px]
    col_all = extended_coordinates(col_coords.to(dt), grid[1] * tile, dc)[cols_px]
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
        U, Vc = pad_gather(u, part), pad_gather(v, part)  # (T_g, K_g)
        P, S = pad_gather(peak, part), pad_gather(rate, part, pad=-1.0)
        blocks.append(tile_blocks(U, Vc, P, S, row_all[group], col_all[group]))
    return assemble_tiles(torch.cat(blocks), used[torch.cat(groups)], n_views, grid, tile, h, w)


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
    dr, dc = uniform_spacing(row_coords, "row_coords"), uniform_spacing(col_coords, "col_coords")
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
    U, Vc, P = pad_gather(centres[..., 0], index), pad_gather(centres[..., 1], index), pad_gather(peak, index)
    inv_k = pad_gather(inv, index, pad=1.0)  # (T, K, 3)
    row_c = extended_coordinates(row_coords.to(dt), grid[0] * tile, dr)[rows_px]
    col_c = extended_coordinates(col_coords.to(dt), grid[1] * tile, dc)[cols_px]
    du = row_c[:, None, :, None] - U[:, :, None, None]  # (T, K, tile, 1)
    dv = col_c[:, None, None, :] - Vc[:, :, None, None]  # (T, K, 1, tile)
    a, b, c = (inv_k[..., j, None, None] for j in range(3))
    blocks = (P[:, :, None, None] * torch.exp(-0.5 * (a * du**2 + 2 * b * du * dv + c * dv**2))).sum(1)
    return assemble_tiles(blocks, used, n_views, grid, tile, h, w)
