"""The views' information about Gaussian atoms and the pull of a residual on them, in closed form.

An atom (position ``r``, width ``sigma``, 3D peak ``q``) is, in a view with detector axes ``P_v``
(2 x 3), the 2D Gaussian ``g(u) = q sigma sqrt(2 pi) exp(-|u - P_v r|^2 / (2 sigma^2))``.  The
pixel sum of the product of two atoms' derivatives (:func:`pair_information`) is the Fisher
information between their parameters (over the pixel noise's variance); the pixel sum of a
residual against an atom's derivatives (:func:`view_scores`) is the pull it leaves on them; the
residual's spectrum says how much more than white noise it weighs at an atom's scale
(:func:`residual_spectrum_factors`).  :mod:`.evidence` builds each atom's evidence from them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from gaussian_atoms_method.physics.geometry import pixel_centres


@dataclass(frozen=True)
class DetectorField:
    """Where each view's detector lies: its rows' and columns' extents about the tilt centre (Å,
    pixel edges) and the tilt centre in the atoms' frame (Å).  The information sums a view only
    over the detector: an atom near a film's edge is seen whole in some views, in part or not at
    all in others, and the whole detector's sum states its precision as if every view held it.

    >>> field = DetectorField.of_views((4, 6), 0.5, (1.5, 2.5), (0.0, 0.0, 0.0))
    >>> field.rows_A, field.cols_A
    ((-1.0, 1.0), (-1.5, 1.5))
    """

    rows_A: tuple[float, float]
    cols_A: tuple[float, float]
    centre_A: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @classmethod
    def of_views(cls, shape_px, pixel_size_A: float, centre_px, origin_A) -> DetectorField:
        """The field of views of ``shape_px`` (H, W), their tilt centre at pixel ``centre_px``
        and at ``origin_A`` in the atoms' frame."""
        centres = centre_px if centre_px is not None else (None, None)
        rows, cols = (pixel_centres(n, pixel_size_A, c) for n, c in zip(shape_px, centres))
        half = pixel_size_A / 2
        edges = [(float(c[0] - half), float(c[-1] + half)) for c in (rows, cols)]
        return cls(edges[0], edges[1], tuple(float(c) for c in origin_A))

    def sight(self, axes):
        """``sight(centres (P, 3), widths (P,)) -> (P, V)``: the share of a 2D Gaussian of each
        width about each centre's image that falls on the detector in each view of ``axes``
        (V, 2, 3), on the centres' device: what :func:`pair_blocks` weighs a pair's view by."""
        host = torch.as_tensor(np.asarray(axes, np.float64)[:, :2, :])
        bounds = torch.tensor([self.rows_A, self.cols_A], dtype=torch.float64)  # (2, 2)
        centre = torch.tensor(self.centre_A, dtype=torch.float64)

        def share(centres: torch.Tensor, widths: torch.Tensor) -> torch.Tensor:
            on = dict(device=centres.device, dtype=centres.dtype)
            at = torch.einsum("pc,vkc->pvk", centres - centre.to(**on), host.to(**on))  # (P, V, 2)
            lo, hi = bounds.to(**on).unbind(1)
            scale = widths.to(**on)[:, None, None]
            return (torch.special.ndtr((hi - at) / scale) - torch.special.ndtr((lo - at) / scale)).prod(-1)

        return share

    def cuts(self, axes, positions_A, sigmas_A) -> bool:
        """Whether the detector cuts any atom's image in any view of ``axes`` by more than 1e-6 of
        it (atoms at ``positions_A`` (N, 3), widths ``sigmas_A`` (N,)): a particle well inside its
        field needs no :meth:`sight`."""
        if len(positions_A) == 0:
            return False
        centres, widths = (torch.as_tensor(np.asarray(a, np.float64)) for a in (positions_A, sigmas_A))
        return bool(self.sight(axes)(centres, widths).min() < 1.0 - 1e-6)


def pair_information(
    r_i, r_j, sigma_i, sigma_j, q_i, q_j, axes, pixel_size_A: float, device=None, sight=None
) -> np.ndarray:
    """``sum_v integral (dg_i/da)(dg_j/db) du / p^2`` for P pairs of atoms: (P, 5, 5) blocks, rows
    the derivatives of atom i by (x, y, z, sigma, q), columns those of atom j.  Divide by the
    pixel noise's variance for the Fisher information.  Read in torch (float64) on ``device``
    (:func:`~gaussian_atoms_method.physics.devices.work_device`; without a GPU on the CPU, where
    it runs twice as fast as numpy's einsums did).

    Parameters
    ----------
    r_i, r_j : (P, 3) arrays, Å
    sigma_i, sigma_j, q_i, q_j : (P,) arrays
        Widths (Å) and 3D peaks (projection units per Å).
    axes : (V, 2, 3) array
        Each view's detector rows and columns in the world.
    pixel_size_A : float
    sight : callable, optional
        :meth:`DetectorField.sight`: each view weighed by the share of the pair's product that
        falls on its detector (None: the whole plane, every atom seen whole in every view).

    Examples
    --------
    One atom alone: its amplitude's information is ``sum_v pi sigma^2 (A/q)^2 / p^2``.

    >>> axes = np.array([[[1.0, 0, 0], [0, 1, 0]]])
    >>> block = pair_information(np.zeros((1, 3)), np.zeros((1, 3)), np.ones(1), np.ones(1),
    ...                          np.ones(1), np.ones(1), axes, 1.0)
    >>> bool(np.isclose(block[0, 4, 4], math.pi * 2 * math.pi))
    True
    """
    from gaussian_atoms_method.physics.devices import work_device

    where = work_device(r_i, device) or torch.device("cpu")
    # a read-only array (an AtomSet's, a memory map) is copied: torch warns on sharing one
    pairs = [
        torch.as_tensor(np.require(a, np.float64, "W"), device=where) for a in (r_i, r_j, sigma_i, sigma_j, q_i, q_j)
    ]
    plane, twice = view_planes(axes, where)
    out = torch.empty((len(pairs[0]), 5, 5), dtype=torch.float64, device=where)
    # on the host a chunk's temporaries stay small enough to be reused, not handed back each time
    chunk = len(out) if where.type != "cpu" else max(1, HOST_PAIR_VIEWS // max(len(plane), 1))
    for start in range(0, len(out), chunk):
        part = slice(start, start + chunk)
        out[part] = pair_blocks(*(a[part] for a in pairs), plane, twice, pixel_size_A, sight)
    return out.cpu().numpy()


def view_planes(axes, device) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`pair_blocks`' view sums: (V, 9) each view's ``P_v^T P_v`` and (V, 81) its outer
    product with itself, float64 on ``device``, of ``axes`` (V, 2 or 3, 3)."""
    axes = torch.as_tensor(np.require(np.asarray(axes, np.float64)[:, :2, :], requirements="W"), device=device)
    plane = torch.einsum("vkc,vkd->vcd", axes, axes).reshape(-1, 9)
    return plane, torch.einsum("vab,vcd->vacbd", *(plane.reshape(-1, 3, 3),) * 2).reshape(-1, 81)


HOST_PAIR_VIEWS = 65536
"""The (pair, view) products :func:`pair_information` reads at once on the host: each of its
temporaries then holds 0.5 MB."""

DEVICE_PAIR_VIEWS = 2**23
"""The (pair, view) products the evidence hands :func:`pair_information` and
:func:`amplitude_coupling` at once on a GPU: each of their temporaries then holds 64 MB, about
1 GB in all.  In pieces of 4,096 pairs, the host's, a 54,000-atom particle took 854 calls and
3.1 s there."""


def pair_blocks(r_i, r_j, sigma_i, sigma_j, q_i, q_j, plane, twice, pixel_size_A: float, sight=None):
    """:func:`pair_information`'s (P, 5, 5) blocks of tensors on one device; ``plane`` (V, 9):
    each view's ``P_v^T P_v``, ``twice`` (V, 81) its outer product with itself
    (:func:`view_planes`).

    With ``d_v = P_v (r_i - r_j)`` the two Gaussians' product sits at ``a_i = -alpha d_v`` from
    ``mu_i`` and ``a_j = beta d_v`` from ``mu_j`` (``alpha``, ``beta`` the widths' shares), so each
    term is a polynomial in ``D_v = |d_v|^2`` of degree two at most times the view's overlap
    ``c_v`` and a pair's constants, and ``P_v^T d_v = P_v^T P_v (r_i - r_j)``: the sums over the
    views are the moments ``sum_v c_v D_v^n`` and matrix products with the views' ``P_v^T P_v``.
    Only ``D`` and ``c`` are read per view (on this CPU, 0.6 of the time the terms took read
    one by one).

    With ``sight`` (:meth:`DetectorField.sight`) each view's terms are weighed by the share of the
    product Gaussian (at ``mu_i + a_i``, width ``tau``) on the detector: exact for a pair seen
    whole or not at all, its moments' change at a cut edge left out."""
    p = len(r_i)
    dr = r_i - r_j  # (P, 3)
    outer = (dr[:, :, None] * dr[:, None, :]).reshape(p, 9)
    big_d = outer @ plane.T  # (P, V): |d_v|^2
    s2i, s2j = sigma_i**2, sigma_j**2
    total = s2i + s2j
    tau2 = s2i * s2j / total
    alpha, beta = s2i / total, s2j / total
    peak = q_i * sigma_i * q_j * sigma_j * 2 * math.pi
    c = torch.exp(big_d * (-0.5 / total)[:, None]) * (2 * math.pi * tau2 * peak / pixel_size_A**2)[:, None]  # (P, V)
    if sight is not None:  # the product sits at beta r_i + alpha r_j
        c = c * sight(beta[:, None] * r_i + alpha[:, None] * r_j, tau2.sqrt())
    cd = c * big_d
    m0, m1, m2 = c.sum(1), cd.sum(1), (cd * big_d).sum(1)  # (P,): sum_v c_v D_v^n
    flat0, flat1 = c @ plane, cd @ plane  # (P, 9): sum_v c_v D_v^n P_v^T P_v
    si, sj, qi, qj, t2, ab, s3i, s3j = sigma_i, sigma_j, q_i, q_j, tau2, alpha * beta, sigma_i**3, sigma_j**3
    out = torch.empty((p, 5, 5), dtype=torch.float64, device=r_i.device)
    # positions: sum_v c_v P_v^T (tau^2 I - alpha beta d_v d_v^T) P_v / (s_i^2 s_j^2)
    spread = ((c @ twice).reshape(p, 9, 9) @ outer[:, :, None]).reshape(p, 9)
    out[:, :3, :3] = ((t2[:, None] * flat0 - ab[:, None] * spread) / (s2i * s2j)[:, None]).reshape(p, 3, 3)
    # the vector terms, (a + b D_v) c_v d_v: d mu_i d sigma_j, d sigma_i d mu_j, d mu_i d q_j, d q_i d mu_j
    shared = 2 * t2 * (beta - alpha)
    a = torch.stack([(shared / s3j - alpha / sj) / s2i, (beta / si + shared / s3i) / s2j, -alpha / (s2i * qj)], 1)
    a = torch.cat([a, (beta / (s2j * qi))[:, None]], 1)
    b = torch.stack([-alpha * beta**2 / (s3j * s2i), beta * alpha**2 / (s3i * s2j), 0 * si, 0 * si], 1)
    sums = a[:, :, None] * flat0[:, None] + b[:, :, None] * flat1[:, None]  # (P, 4, 9)
    rows = sums.reshape(p, 4, 3, 3) @ dr[:, None, :, None]  # (P, 4, 3, 1): sum_v t_v P_v^T d_v
    out[:, :3, 3], out[:, 3, :3], out[:, :3, 4], out[:, 4, :3] = rows[..., 0].unbind(1)
    # E|w + a_i|^2 = 2 tau^2 + alpha^2 D, E|w + a_j|^2 = 2 tau^2 + beta^2 D, and the product's
    # 8 tau^4 + 2 tau^2 (alpha - beta)^2 D + alpha^2 beta^2 D^2
    out[:, 3, 3] = (
        (1 / (si * sj) + 2 * t2 / (si * s3j) + 2 * t2 / (s3i * sj) + 8 * t2**2 / (s3i * s3j)) * m0
        + (beta**2 / (si * s3j) + alpha**2 / (s3i * sj) + 2 * t2 * (alpha - beta) ** 2 / (s3i * s3j)) * m1
        + ab**2 / (s3i * s3j) * m2
    )
    out[:, 3, 4] = ((1 / si + 2 * t2 / s3i) * m0 + alpha**2 / s3i * m1) / qj
    out[:, 4, 3] = ((1 / sj + 2 * t2 / s3j) * m0 + beta**2 / s3j * m1) / qi
    out[:, 4, 4] = m0 / (qi * qj)
    return out


def amplitude_coupling(r_i, r_j, sigma_i, sigma_j, axes, device=None) -> np.ndarray:
    """(P,) how much the views confuse two atoms' amplitudes: ``|F_qiqj| / sqrt(F_qiqi F_qjqj)``
    of :func:`pair_information`'s blocks, without the rest of them (a tenth of their work:
    the pairs an atom's evidence may leave out are found with it).  For two Gaussians the views'
    overlap is ``sum_v exp(-|P_v (r_i - r_j)|^2 / (2 T)) 2 sigma_i sigma_j / (T V)``,
    ``T = sigma_i^2 + sigma_j^2``: 1 for an atom with itself.  In torch (float64) on ``device``
    (default the CPU, where it runs four times as fast as numpy's einsums did; on a GPU's host
    numpy had taken 2.3 of the 19 s a 54,000-atom particle's evidence took)."""
    on = lambda a: torch.as_tensor(np.require(a, np.float64, "W"), device=device or "cpu")  # noqa: E731
    axes = on(np.asarray(axes, dtype=np.float64)[:, :2, :])
    s_i, s_j = on(sigma_i), on(sigma_j)
    total = s_i**2 + s_j**2
    d = torch.einsum("vkc,pc->pvk", axes, on(r_i) - on(r_j))
    overlap = torch.exp(-(d * d).sum(dim=2) / (2 * total[:, None])).sum(dim=1)
    return (overlap * 2 * s_i * s_j / (total * len(axes))).cpu().numpy()


def view_scores(
    positions_A: np.ndarray,
    sigmas_A: np.ndarray,
    amplitudes: np.ndarray,
    detector_axes: np.ndarray,
    residuals,
    pixel_size_A: float,
    centre_px,
    reach_sigmas: float = 4.0,
    device=None,
) -> np.ndarray:
    """Each view's pull on each atom: ``sum_pixels r_v(u) dg/d(x, y, z, sigma, q)`` over the view's
    residual ``r_v``, (N, V, 5).  Their spread over the views is what the residual that is there
    does to the fit (:func:`atom_evidence`'s sandwich); pixels beyond ``reach_sigmas`` widths of an
    atom's centre are left out (its derivatives hold under 1e-3 of their weight there).  Read on
    ``device`` (:func:`~gaussian_atoms_method.physics.devices.work_device`: a tensor's own, else a
    GPU where there is one) in torch, every view at once for a batch of atoms; without one with
    numpy on the host.

    Parameters
    ----------
    positions_A : (N, 3) array, Å about the tilt centre
    sigmas_A, amplitudes : (N,) arrays
    detector_axes : (V, 2, 3) or (V, 3, 3) array
    residuals : (V, H, W) array or tensor
        Measured minus predicted views, projection units.
    pixel_size_A : float
    centre_px : (2,) the detector pixel of the tilt centre
    """
    from gaussian_atoms_method.physics.devices import work_device
    from gaussian_atoms_method.physics.noise import as_array

    where = work_device(residuals, device)
    res = torch.as_tensor(residuals).to(where, torch.float64) if where is not None else as_array(residuals)
    axes = np.asarray(detector_axes, dtype=np.float64)[:, :2, :]
    positions = np.asarray(positions_A, np.float64).reshape(-1, 3)
    sigmas, amps = np.asarray(sigmas_A, np.float64).ravel(), np.asarray(amplitudes, np.float64).ravel()
    out = np.zeros((len(positions), res.shape[0], 5))
    reach = np.ceil(reach_sigmas * sigmas / pixel_size_A).astype(np.int64) + 1
    # atoms of one reach together: one wide Gaussian does not widen every atom's window
    for size in np.unique(reach):
        group = np.flatnonzero(reach == size)
        if where is None:
            out[group] = _view_scores_host(
                positions[group], sigmas[group], amps[group], axes, res, pixel_size_A, centre_px, int(size)
            )
            continue
        batch = max(1, int(SCORE_ELEMENTS // (res.shape[0] * (2 * size + 1) ** 2)))
        for start in range(0, len(group), batch):
            chosen = group[start : start + batch]
            picked = (positions[chosen], sigmas[chosen], amps[chosen], axes)
            tensors = (torch.as_tensor(a, device=where) for a in picked)
            out[chosen] = _view_scores(*tensors, res, pixel_size_A, centre_px, int(size)).cpu().numpy()
    return out


SCORE_ELEMENTS = 2e7
"""The most window pixels (atoms x views x window) :func:`view_scores` reads at once (each a
float64 of a temporary)."""


def _view_scores(positions, sigmas, amps, axes, res, pixel_size_A: float, centre_px, reach: int):
    """:func:`view_scores` of (N,) atoms whose windows reach ``reach`` pixels from their centres:
    (N, V, 5) tensors on ``res``'s device, every view at once."""
    v_count, h, w = res.shape
    offsets = torch.arange(-reach, reach + 1, device=res.device)
    centre = torch.as_tensor(np.asarray(centre_px, np.float64), device=res.device)
    peak = amps * sigmas * math.sqrt(2 * math.pi)
    mu = torch.einsum("vkc,nc->nvk", axes, positions)  # (N, V, 2) Å on the detector
    centre_pixel = torch.round(mu / pixel_size_A + centre).long()
    rows = centre_pixel[..., 0, None] + offsets  # (N, V, R)
    cols = centre_pixel[..., 1, None] + offsets
    inside = ((rows >= 0) & (rows < h))[..., :, None] & ((cols >= 0) & (cols < w))[..., None, :]
    flat = (torch.arange(v_count, device=res.device)[None, :, None, None] * h + rows.clamp(0, h - 1)[..., None]) * w
    values = torch.where(inside, res.reshape(-1)[flat + cols.clamp(0, w - 1)[..., None, :]], 0.0)  # (N, V, R, R)
    du = (rows - centre[0]) * pixel_size_A - mu[..., :1]  # (N, V, R) u - mu along rows
    dw = (cols - centre[1]) * pixel_size_A - mu[..., 1:]
    d2 = du[..., :, None] ** 2 + dw[..., None, :] ** 2
    s = sigmas[:, None, None, None]
    g = peak[:, None, None, None] * torch.exp(-d2 / (2 * s**2)) * values  # r g
    pull_row = (g * du[..., :, None]).sum((2, 3)) / sigmas[:, None] ** 2  # (N, V)
    pull_col = (g * dw[..., None, :]).sum((2, 3)) / sigmas[:, None] ** 2
    out = torch.empty(positions.shape[0], v_count, 5, dtype=torch.float64, device=res.device)
    out[..., :3] = pull_row[..., None] * axes[:, 0] + pull_col[..., None] * axes[:, 1]
    out[..., 3] = (g * (1 / s + d2 / s**3)).sum((2, 3))
    out[..., 4] = g.sum((2, 3)) / amps[:, None]
    return out


def _view_scores_host(positions, sigmas, amps, axes, res, pixel_size_A, centre_px, reach: int) -> np.ndarray:
    """:func:`view_scores` of atoms whose windows reach ``reach`` pixels from their centres, with
    numpy on the host, a view at a time and :data:`HOST_SCORE_ATOMS` atoms at a time (their
    temporaries stay in the cache, and none is large enough to be handed back to the system each
    time: on the 6,679-atom Au particle the whole-set temporaries cost more system than user
    time).  Each window is a view into the view padded with zeros (a pixel beyond the detector
    weighs nothing), and the Gaussian is separable: a window is summed against its columns'
    weights first (one batched product), then its rows'."""
    from concurrent.futures import ThreadPoolExecutor

    from numpy.lib.stride_tricks import sliding_window_view

    from gaussian_atoms_method.physics.devices import cores_given

    v_count, h, w = res.shape
    size = 2 * reach + 1
    out = np.zeros((len(positions), v_count, 5))
    centre = np.asarray(centre_px, np.float64)
    pad = size + 1  # a window about a centre clipped to within reach + 1 of the detector lies in the zeros
    offsets = np.arange(-reach, reach + 1)

    def views(chosen) -> None:
        padded = np.zeros((h + 2 * pad, w + 2 * pad))  # each worker its own
        for v in chosen:
            padded[pad:-pad, pad:-pad] = np.asarray(res[v])
            windows = sliding_window_view(padded, (size, size))  # [i, j]: the window whose corner is (i, j)
            mu = positions @ axes[v].T  # (N, 2) Å on the detector
            centre_pixel = np.rint(mu / pixel_size_A + centre).astype(np.int64)
            row0 = np.clip(centre_pixel[:, 0], -reach - 1, h + reach) - reach + pad
            col0 = np.clip(centre_pixel[:, 1], -reach - 1, w + reach) - reach + pad
            for start in range(0, len(positions), HOST_SCORE_ATOMS):
                part = slice(start, start + HOST_SCORE_ATOMS)
                s, a = sigmas[part], amps[part]
                peak = a * s * math.sqrt(2 * math.pi)
                values = windows[row0[part], col0[part]]  # (N, R, R)
                du = (centre_pixel[part, 0, None] + offsets - centre[0]) * pixel_size_A - mu[part, :1]  # (N, R)
                dw = (centre_pixel[part, 1, None] + offsets - centre[1]) * pixel_size_A - mu[part, 1:]
                er = np.exp(-(du**2) / (2 * s[:, None] ** 2))
                ec = np.exp(-(dw**2) / (2 * s[:, None] ** 2))
                by_col = values @ np.stack([ec, ec * dw, ec * dw**2], axis=2)  # (N, R, 3)
                total = np.einsum("nr,nr->n", er, by_col[..., 0])
                along_row = np.einsum("nr,nr->n", er * du, by_col[..., 0])
                along_col = np.einsum("nr,nr->n", er, by_col[..., 1])
                d2 = np.einsum("nr,nr->n", er * du**2, by_col[..., 0]) + np.einsum("nr,nr->n", er, by_col[..., 2])
                pull_row, pull_col = peak * along_row / s**2, peak * along_col / s**2
                out[part, v, :3] = pull_row[:, None] * axes[v, 0] + pull_col[:, None] * axes[v, 1]
                out[part, v, 3] = peak * (total / s + d2 / s**3)
                out[part, v, 4] = peak * total / a

    workers = max(1, min(cores_given(), v_count))
    if workers == 1:
        views(range(v_count))
    else:  # numpy lets the GIL go in its loops: the views split between the cores, joined here
        with ThreadPoolExecutor(workers) as pool:
            list(pool.map(views, [range(k, v_count, workers) for k in range(workers)]))
    return out


HOST_SCORE_ATOMS = 256
"""The atoms :func:`_view_scores_host` reads at once: a window of 33 x 33 pixels (a width of 0.5 Å
at 0.25 Å pixels) holds 2.2 MB of them, within a core's cache."""


def residual_spectrum_factors(residuals, noise_std: float, sigma_px: float) -> tuple[float, float]:
    """How much more the residual weighs at the atoms' scale than white noise of ``noise_std``:
    for a matched template ``t`` (an atom's image, or its derivative along a detector axis) the
    variance of its fit under noise of power spectrum ``P(k)`` is ``sum |T(k)|^2 P(k)`` against
    ``s^2 sum |T(k)|^2`` for white noise.  Returns the square roots for the position's template
    (``|T|^2 ~ k^2 exp(-k^2 sigma^2)``) and the amplitude's (``exp(-k^2 sigma^2)``): 1 for white
    noise of ``noise_std``, above 1 where the residual holds more at the atoms' scale (a smooth
    misfit weighs on the amplitude, a grainy one on the position).

    Parameters
    ----------
    residuals : (V, H, W) array or tensor
        Measured minus predicted views, projection units (a tensor is read where it lies).
    noise_std : float
        The level the evidence assumes (white), projection units.
    sigma_px : float
        The atoms' typical width, pixels.
    """
    res = torch.as_tensor(residuals).double()
    res = res - res.mean(dim=(1, 2), keepdim=True)
    h, w = res.shape[1:]
    power = (torch.fft.fft2(res).abs() ** 2).mean(dim=0) / (h * w)  # white noise of s: s^2 at every k
    ky = 2 * math.pi * torch.fft.fftfreq(h, device=res.device, dtype=res.dtype)
    kx = 2 * math.pi * torch.fft.fftfreq(w, device=res.device, dtype=res.dtype)
    k2 = ky[:, None] ** 2 + kx[None, :] ** 2
    amplitude_template = torch.exp(-k2 * sigma_px**2)
    position_template = k2 * amplitude_template
    s2 = noise_std**2
    amplitude = float((amplitude_template * power).sum() / (s2 * amplitude_template.sum()))
    position = float((position_template * power).sum() / (s2 * position_template.sum()))
    return math.sqrt(max(position, 0.0)), math.sqrt(max(amplitude, 0.0))


BATCH_ELEMENTS = 2e7
"""The most float64 numbers a batch of atoms' local information holds with its moved copies on
a GPU; atoms of as many neighbours are solved together."""

HOST_BATCH_ELEMENTS = 4e6
""":data:`BATCH_ELEMENTS` on the host: a batch's temporaries (32 MB) are still reused, not handed
back to the system each time (on the 6,679-atom Au particle 2e7 cost more system than user time),
and its batches of about 46 atoms pay the per-batch work of the depth profile a quarter as often
as batches of 1e6 did (its evidence 13.7 s against 15.0 s on this CPU, alternated three times,
system time alike; the same evidence to 1e-13 of the profile's scale)."""


def _adjacency(neighbours: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each of ``n`` atoms' neighbours (``neighbours`` (P, 2), either way round): ``cols`` (2P,)
    the neighbours grouped by atom, ascending within each, ``degree`` (n,) how many each atom
    has, ``first`` (n + 1,) where its group starts in ``cols``."""
    rows, cols = np.r_[neighbours[:, 0], neighbours[:, 1]], np.r_[neighbours[:, 1], neighbours[:, 0]]
    order = np.lexsort((cols, rows))
    degree = np.bincount(rows, minlength=n)
    return cols[order], degree, np.r_[0, np.cumsum(degree)]


def pairs_among_neighbours(neighbours: np.ndarray, n: int, wanted: np.ndarray | None = None, device=None) -> np.ndarray:
    """(Q, 2) the pairs of atoms, first < second, that are both neighbours of one ``wanted`` atom
    (indices; default all; ``neighbours`` (P, 2) of ``n`` atoms) and not neighbours of each
    other: the blocks an atom's set holds beyond its own.  Without them the set's information is
    no principal submatrix of the whole one and need not be positive definite: on a 1,512-atom
    carbon particle every set's was not (its smallest eigenvalue -0.5 of the diagonal's scale),
    and an atom's amplitude variance came out negative for 30% of them.  Found in torch on
    ``device`` (default the CPU; on a GPU's host the search had taken 1.8 of the 9 s a
    54,000-atom particle's evidence took); integer keys, so the same pairs on any device."""
    if len(neighbours) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    cols, degree, first = _adjacency(neighbours, n)
    wanted = np.arange(n) if wanted is None else np.asarray(wanted)
    device = device or "cpu"
    at = lambda a: torch.as_tensor(np.asarray(a, np.int64), device=device)  # noqa: E731
    cols_on, found = at(cols), [torch.zeros(0, dtype=torch.int64, device=device)]
    for k in np.unique(degree[wanted]):
        if k < 2:
            continue
        atoms = wanted[degree[wanted] == k]
        sets = cols_on[at(first[atoms])[:, None] + torch.arange(int(k), device=device)]  # (B, k), rows ascending
        a, b = torch.triu_indices(int(k), int(k), 1, device=device)
        found.append(torch.unique(sets[:, a] * n + sets[:, b]))
    keys = torch.unique(torch.cat(found))
    own = np.minimum(neighbours[:, 0], neighbours[:, 1]) * n + np.maximum(neighbours[:, 0], neighbours[:, 1])
    keys = keys[~torch.isin(keys, at(own))]
    return torch.stack([keys // n, keys % n], dim=1).cpu().numpy().astype(np.int64)


def local_information(
    wanted, neighbours, pairs, blocks, diagonal, n_offsets: int, budget: float | None = None, device=None
):
    """The information of each wanted atom with its neighbours, in batches of atoms with as many
    neighbours: yields ``(atoms (B,), local (B, k), info (B, 5k, 5k))``, ``local[:, 0]`` the atom,
    the rest its neighbours (the atoms ``neighbours`` (P, 2) join it to), ``info`` their (5, 5)
    blocks: ``diagonal`` (N, 5, 5) on the diagonal, ``blocks`` (Q, 5, 5) (rows: the pair's first
    atom) between the ``pairs`` (Q, 2) (:func:`pairs_among_neighbours` with them: every pair
    within a set), zero between any others; a float64 tensor on ``device`` (default the CPU),
    assembled there (on a GPU its assembly on the host had taken 16 of the 50 s a 76,000-atom
    particle's evidence took).  A batch holds at most ``budget`` numbers with its ``n_offsets``
    moved copies (:func:`.depth_profile.depth_rises`; default :data:`BATCH_ELEMENTS`)."""
    n = len(diagonal)
    on = dict(dtype=torch.float64, device=device or "cpu")
    # each ordered pair's block, sorted by its key: on the device (a GPU's host had taken 2.8 s
    # of a 54,000-atom particle's evidence reordering the blocks there)
    keys = torch.as_tensor(np.r_[pairs[:, 0] * n + pairs[:, 1], pairs[:, 1] * n + pairs[:, 0]], device=on["device"])
    keys, order = torch.sort(keys, stable=True)
    one_way = torch.as_tensor(np.require(blocks, np.float64, "W"), **on)
    both = torch.cat([one_way, one_way.transpose(1, 2)])[order]
    del one_way
    diagonal = torch.as_tensor(diagonal, **on)
    for atoms, local in local_sets(wanted, neighbours, n, n_offsets, budget):
        k = local.shape[1]
        near = torch.as_tensor(local, device=on["device"])
        info = torch.zeros((len(atoms), k, k, 5, 5), **on)
        slots = torch.arange(k, device=on["device"])
        info[:, slots, slots] = diagonal[near]
        if k > 1 and len(keys):
            key = near[:, :, None] * n + near[:, None, :]
            at = torch.searchsorted(keys, key).clamp_max(len(keys) - 1)
            hit = keys[at] == key
            hit[:, slots, slots] = False
            info[hit] = both[at[hit]]
        yield atoms, local, info.permute(0, 1, 3, 2, 4).reshape(len(atoms), 5 * k, 5 * k)


def local_sets(wanted, neighbours, n: int, n_offsets: int = 0, budget: float | None = None):
    """:func:`local_information`'s batches without the information: ``(atoms (B,), local (B, k))``
    of the ``wanted`` atoms among ``n``, in the same order."""
    budget = BATCH_ELEMENTS if budget is None else budget
    near_cols, degree, first = _adjacency(neighbours, n)
    for others in np.unique(degree[wanted]):
        group, k = wanted[degree[wanted] == others], int(others) + 1
        size = max(1, int(budget // (25 * k * k * (1 + n_offsets))))
        for c in range(0, len(group), size):
            atoms = group[c : c + size]
            yield atoms, np.c_[atoms, near_cols[first[atoms][:, None] + np.arange(others)]].astype(np.int64)
