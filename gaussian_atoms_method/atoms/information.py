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

import numpy as np
import torch


def _gaussian_products(mu_i, mu_j, s_i, s_j):
    """Product of two 2D Gaussians of centres ``mu`` (..., 2) and widths ``s`` (...): the
    weight ``exp(-|mu_i - mu_j|^2 / (2 S)) 2 pi tau^2`` and the offsets ``a = m - mu`` of each centre
    from the product's centre ``m``, and ``tau^2``."""
    s2i, s2j = s_i**2, s_j**2
    total = s2i + s2j
    tau2 = s2i * s2j / total
    d = mu_i - mu_j
    weight = torch.exp(-torch.einsum("...k,...k->...", d, d) / (2 * total)) * 2 * math.pi * tau2
    m = (mu_i * s2j[..., None] + mu_j * s2i[..., None]) / total[..., None]
    return weight, m - mu_i, m - mu_j, tau2


def pair_information(r_i, r_j, sigma_i, sigma_j, q_i, q_j, axes, pixel_size_A: float, device=None) -> np.ndarray:
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
    axes = torch.as_tensor(np.require(np.asarray(axes, np.float64)[:, :2, :], requirements="W"), device=where)
    r_i, r_j, sigma_i, sigma_j, q_i, q_j = (
        torch.as_tensor(np.require(a, np.float64, "W"), device=where) for a in (r_i, r_j, sigma_i, sigma_j, q_i, q_j)
    )
    mu_i = torch.einsum("vkc,pc->pvk", axes, r_i)  # (P, V, 2)
    mu_j = torch.einsum("vkc,pc->pvk", axes, r_j)
    si, sj = sigma_i[:, None].expand(mu_i.shape[:2]), sigma_j[:, None].expand(mu_i.shape[:2])
    weight, a_i, a_j, tau2 = _gaussian_products(mu_i, mu_j, si, sj)
    peak_i, peak_j = q_i * sigma_i * math.sqrt(2 * math.pi), q_j * sigma_j * math.sqrt(2 * math.pi)
    c = weight * (peak_i * peak_j)[:, None] / pixel_size_A**2  # (P, V)
    s2i, s2j = si**2, sj**2
    eye = torch.eye(2, dtype=torch.float64, device=where)
    # E[(w + a_i)(w + a_j)^T] = tau^2 I + a_i a_j^T, over sigma_i^2 sigma_j^2
    mm = (tau2[..., None, None] * eye + a_i[..., :, None] * a_j[..., None, :]) / (s2i * s2j)[..., None, None]
    ai2, aj2, aiaj = (a_i**2).sum(-1), (a_j**2).sum(-1), (a_i * a_j).sum(-1)
    ex, ey = 2 * tau2 + ai2, 2 * tau2 + aj2  # E|w + a_i|^2, E|w + a_j|^2
    exy = 8 * tau2**2 + 2 * tau2 * (ai2 + aj2) + 4 * tau2 * aiaj + ai2 * aj2
    # E[(w + a_i) |w + a_j|^2] = 2 tau^2 a_j + a_i (2 tau^2 + |a_j|^2), and with i, j exchanged
    wi_yj = 2 * tau2[..., None] * a_j + a_i * ey[..., None]
    wj_xi = 2 * tau2[..., None] * a_i + a_j * ex[..., None]
    mu_sigma = (a_i / sj[..., None] + wi_yj / (sj**3)[..., None]) / s2i[..., None]  # d mu_i, d sigma_j
    sigma_mu = (a_j / si[..., None] + wj_xi / (si**3)[..., None]) / s2j[..., None]  # d sigma_i, d mu_j
    ss = 1 / (si * sj) + ey / (si * sj**3) + ex / (si**3 * sj) + exy / (si**3 * sj**3)
    qi, qj = q_i[:, None], q_j[:, None]
    mu_q = a_i / (s2i * qj)[..., None]  # d mu_i, d q_j
    q_mu = a_j / (s2j * qi)[..., None]  # d q_i, d mu_j
    sigma_q = (1 / si + ex / si**3) / qj
    q_sigma = (1 / sj + ey / sj**3) / qi
    qq = 1 / (qi * qj) * torch.ones_like(si)
    out = torch.zeros((len(r_i), 5, 5), dtype=torch.float64, device=where)
    # positions: P_v^T (.) P_v, summed over the views with the weights c
    out[:, :3, :3] = torch.einsum("pv,vkc,pvkl,vld->pcd", c, axes, mm, axes)
    out[:, :3, 3] = torch.einsum("pv,vkc,pvk->pc", c, axes, mu_sigma)
    out[:, 3, :3] = torch.einsum("pv,vkc,pvk->pc", c, axes, sigma_mu)
    out[:, :3, 4] = torch.einsum("pv,vkc,pvk->pc", c, axes, mu_q)
    out[:, 4, :3] = torch.einsum("pv,vkc,pvk->pc", c, axes, q_mu)
    out[:, 3, 3] = (c * ss).sum(1)
    out[:, 3, 4] = (c * sigma_q).sum(1)
    out[:, 4, 3] = (c * q_sigma).sum(1)
    out[:, 4, 4] = (c * qq).sum(1)
    return out.cpu().numpy()


def amplitude_coupling(r_i, r_j, sigma_i, sigma_j, axes) -> np.ndarray:
    """(P,) how much the views confuse two atoms' amplitudes: ``|F_qiqj| / sqrt(F_qiqi F_qjqj)``
    of :func:`pair_information`'s blocks, without the rest of them (a tenth of their work:
    the pairs an atom's evidence may leave out are found with it).  For two Gaussians the views'
    overlap is ``sum_v exp(-|P_v (r_i - r_j)|^2 / (2 T)) 2 sigma_i sigma_j / (T V)``,
    ``T = sigma_i^2 + sigma_j^2``: 1 for an atom with itself."""
    axes = np.asarray(axes, dtype=np.float64)[:, :2, :]
    sigma_i, sigma_j = np.asarray(sigma_i, np.float64), np.asarray(sigma_j, np.float64)
    d = np.einsum("vkc,pc->pvk", axes, np.asarray(r_i, np.float64) - np.asarray(r_j, np.float64))
    total = sigma_i**2 + sigma_j**2
    overlap = np.exp(-np.einsum("pvk,pvk->pv", d, d) / (2 * total[:, None])).sum(axis=1)
    return overlap * 2 * sigma_i * sigma_j / (total * len(axes))


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
    size_of = 2 ** np.ceil(np.log2(np.maximum(reach, 1))).astype(np.int64)
    # atoms of like reach together: one wide Gaussian does not widen every atom's window
    for size in np.unique(size_of):
        group = np.flatnonzero(size_of == size)
        if where is None:
            out[group] = _view_scores_host(
                positions[group], sigmas[group], amps[group], axes, res, pixel_size_A, centre_px, size
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
    numpy on the host, a view at a time (its temporaries stay in the cache, where the batched
    torch reading's do not)."""
    v_count, h, w = res.shape
    offsets = np.arange(-reach, reach + 1)
    out = np.zeros((len(positions), v_count, 5))
    peak = amps * sigmas * math.sqrt(2 * math.pi)
    for v in range(v_count):
        mu = positions @ axes[v].T  # (N, 2) Å on the detector
        centre_pixel = np.rint(mu / pixel_size_A + np.asarray(centre_px, np.float64)).astype(np.int64)
        rows = centre_pixel[:, 0, None] + offsets[None]  # (N, R)
        cols = centre_pixel[:, 1, None] + offsets[None]
        inside = (rows[:, :, None] >= 0) & (rows[:, :, None] < h) & (cols[:, None, :] >= 0) & (cols[:, None, :] < w)
        values = np.where(inside, res[v][np.clip(rows, 0, h - 1)[:, :, None], np.clip(cols, 0, w - 1)[:, None, :]], 0)
        du = (rows - np.asarray(centre_px)[0]) * pixel_size_A - mu[:, :1]  # (N, R) u - mu along rows
        dw = (cols - np.asarray(centre_px)[1]) * pixel_size_A - mu[:, 1:]
        d2 = du[:, :, None] ** 2 + dw[:, None, :] ** 2
        s2 = sigmas[:, None, None] ** 2
        g = peak[:, None, None] * np.exp(-d2 / (2 * s2)) * values  # r g
        pull_row = (g * du[:, :, None]).sum((1, 2)) / sigmas**2
        pull_col = (g * dw[:, None, :]).sum((1, 2)) / sigmas**2
        out[:, v, :3] = pull_row[:, None] * axes[v, 0] + pull_col[:, None] * axes[v, 1]
        out[:, v, 3] = (g * (1 / sigmas[:, None, None] + d2 / sigmas[:, None, None] ** 3)).sum((1, 2))
        out[:, v, 4] = g.sum((1, 2)) / amps
    return out


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
"""The most float64 numbers a batch of atoms' local information holds with its moved copies;
atoms of as many neighbours are solved together."""


def _adjacency(neighbours: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each of ``n`` atoms' neighbours (``neighbours`` (P, 2), either way round): ``cols`` (2P,)
    the neighbours grouped by atom, ascending within each, ``degree`` (n,) how many each atom
    has, ``first`` (n + 1,) where its group starts in ``cols``."""
    rows, cols = np.r_[neighbours[:, 0], neighbours[:, 1]], np.r_[neighbours[:, 1], neighbours[:, 0]]
    order = np.lexsort((cols, rows))
    degree = np.bincount(rows, minlength=n)
    return cols[order], degree, np.r_[0, np.cumsum(degree)]


def pairs_among_neighbours(neighbours: np.ndarray, n: int, wanted: np.ndarray | None = None) -> np.ndarray:
    """(Q, 2) the pairs of atoms, first < second, that are both neighbours of one ``wanted`` atom
    (indices; default all; ``neighbours`` (P, 2) of ``n`` atoms) and not neighbours of each
    other: the blocks an atom's set holds beyond its own.  Without them the set's information is
    no principal submatrix of the whole one and need not be positive definite: on a 1,512-atom
    carbon particle every set's was not (its smallest eigenvalue -0.5 of the diagonal's scale),
    and an atom's amplitude variance came out negative for 30% of them."""
    if len(neighbours) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    cols, degree, first = _adjacency(neighbours, n)
    wanted = np.arange(n) if wanted is None else np.asarray(wanted)
    found = [np.zeros(0, dtype=np.int64)]
    for k in np.unique(degree[wanted]):
        if k < 2:
            continue
        atoms = wanted[degree[wanted] == k]
        sets = cols[first[atoms][:, None] + np.arange(k)]  # (B, k), each row ascending
        a, b = np.triu_indices(int(k), 1)
        found.append(np.unique(sets[:, a] * n + sets[:, b]))
    keys = np.unique(np.concatenate(found))
    own = np.minimum(neighbours[:, 0], neighbours[:, 1]) * n + np.maximum(neighbours[:, 0], neighbours[:, 1])
    keys = keys[~np.isin(keys, own)]
    return np.stack([keys // n, keys % n], axis=1).astype(np.int64)


def local_information(wanted, neighbours, pairs, blocks, diagonal, n_offsets: int, budget: float | None = None):
    """The information of each wanted atom with its neighbours, in batches of atoms with as many
    neighbours: yields ``(atoms (B,), local (B, k), info (B, 5k, 5k))``, ``local[:, 0]`` the atom,
    the rest its neighbours (the atoms ``neighbours`` (P, 2) join it to), ``info`` their (5, 5)
    blocks: ``diagonal`` (N, 5, 5) on the diagonal, ``blocks`` (Q, 5, 5) (rows: the pair's first
    atom) between the ``pairs`` (Q, 2) (:func:`pairs_among_neighbours` with them: every pair
    within a set), zero between any others.  A batch holds at most ``budget`` numbers with its
    ``n_offsets`` moved copies (:func:`.depth_profile.depth_rises`; default :data:`BATCH_ELEMENTS`)."""
    budget = BATCH_ELEMENTS if budget is None else budget
    n = len(diagonal)
    keys = np.r_[pairs[:, 0] * n + pairs[:, 1], pairs[:, 1] * n + pairs[:, 0]]
    both = np.concatenate([blocks, blocks.transpose(0, 2, 1)])  # the (row, col) block of each ordered pair
    order = np.argsort(keys)
    keys, both = keys[order], both[order]
    near_cols, degree, first = _adjacency(neighbours, n)
    for others in np.unique(degree[wanted]):
        group, k = wanted[degree[wanted] == others], int(others) + 1
        size = max(1, int(budget // (25 * k * k * (1 + n_offsets))))
        for c in range(0, len(group), size):
            atoms = group[c : c + size]
            local = np.c_[atoms, near_cols[first[atoms][:, None] + np.arange(others)]].astype(np.int64)
            info = np.zeros((len(atoms), k, k, 5, 5))
            slots = np.arange(k)
            info[:, slots, slots] = diagonal[local]
            if others:
                key = local[:, :, None] * n + local[:, None, :]
                at = np.minimum(np.searchsorted(keys, key), len(keys) - 1)
                hit = keys[at] == key
                hit[:, slots, slots] = False
                info[hit] = both[at[hit]]
            yield atoms, local, info.transpose(0, 1, 3, 2, 4).reshape(len(atoms), 5 * k, 5 * k)
