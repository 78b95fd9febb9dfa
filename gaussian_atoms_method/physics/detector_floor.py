"""The detector's floor under the views: a constant or a smooth surface read from the frame of
each view (where the views hold only background), with the clipping that keeps atoms reaching
the frame out of the reading.  The data term's background starts from it
(:mod:`gaussian_atoms_method.engine.noise_reading`)."""

from __future__ import annotations

import numpy as np


def frame_mask(shape: tuple[int, int], frame_fraction: float = 0.08) -> np.ndarray:
    """(H, W) bool: the outer frame, ``frame_fraction`` of the shorter side (at least one pixel)."""
    h, w = shape
    k = max(1, int(round(frame_fraction * min(h, w))))
    mask = np.zeros((h, w), dtype=bool)
    mask[:k], mask[-k:], mask[:, :k], mask[:, -k:] = True, True, True, True
    return mask


def quadratic_basis(shape: tuple[int, int]) -> np.ndarray:
    """(6, H, W): 1, r, c, r^2, r c, c^2 over the pixel indices scaled to [-1, 1]."""
    r, c = np.meshgrid(np.linspace(-1.0, 1.0, shape[0]), np.linspace(-1.0, 1.0, shape[1]), indexing="ij")
    return np.stack([np.ones_like(r), r, c, r * r, r * c, c * c])


def frame_surfaces(projections: np.ndarray, frame_fraction: float = 0.08) -> tuple[np.ndarray, float]:
    """A smooth floor under every view, read where the views hold only background.

    Per view, the least-squares quadratic surface (in the pixel indices scaled to [-1, 1]) through
    the outer frame (:func:`frame_mask`), evaluated over the whole detector: a support film's or
    a phase image's floor that varies within the view, as far as the frame shows it.

    Returns
    -------
    surfaces : (N, H, W) array
    frame_variance : float
        The frame pixels' variance about their view's surface: about the noise variance at the
        floor when the frame is smooth background, far more when atoms reach it.
    """
    p = np.asarray(projections, dtype=np.float64)
    basis = quadratic_basis(p.shape[-2:])
    mask = frame_mask(p.shape[-2:], frame_fraction)
    coef, *_ = np.linalg.lstsq(basis[:, mask].T, p[:, mask].T, rcond=None)  # (6, N)
    surfaces = np.einsum("kn,khw->nhw", coef, basis)
    return surfaces, float((p[:, mask] - surfaces[:, mask]).var())


CLIP_Z = 3.0
"""A frame pixel this many noise standard deviations above its view's surface holds signal, not
background (:func:`clipped_frame`): a chance of 0.13% for a pixel of Gaussian noise, so the
clipping leaves the floor's mean within 0.01 standard deviations of the truth."""


def masked_least_squares(basis: np.ndarray, values: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """(N, K) least-squares coefficients of each row of ``values`` (N, F) on the (F, K)
    ``basis``, over the pixels ``keep`` (N, F) marks, for all rows at once: the normal equations,
    solved by pseudo-inverse (a row with too few pixels gets the minimum-norm fit, as
    ``np.linalg.lstsq``).  The quadratic basis on [-1, 1] is well conditioned, so this equals
    lstsq per row to 1e-10 (test_noise), without a solve per view."""
    w = keep.astype(np.float64)
    k = basis.shape[1]
    gram = (w @ (basis[:, :, None] * basis[:, None, :]).reshape(len(basis), k * k)).reshape(-1, k, k)
    return (np.linalg.pinv(gram, hermitian=True) @ ((w * values) @ basis)[..., None])[..., 0]


def clipped_frame(
    projections: np.ndarray, noise_std: float, frame_fraction: float = 0.08, max_rounds: int = 10
) -> tuple[np.ndarray, float, float, float, float]:
    """The floor read from the frame pixels that hold only background, where atoms reach the frame.

    Every atom adds to a projection and none takes away (a projected potential and an ADF
    intensity are non-negative), so the frame pixels an atom reaches stand above the floor and
    the floor is the frame's lower envelope: per view, the least-squares quadratic surface
    through the frame (:func:`frame_surfaces`) is fitted again without the pixels more than
    :data:`CLIP_Z` ``noise_std`` above it, until no pixel changes side.  A frame of background
    keeps nearly all its pixels; where a probe's tails carry atoms into the frame, the kept
    pixels vary about their surfaces as the noise does, and far more with every pixel kept.

    Returns
    -------
    surfaces : (N, H, W) array
    floor, standard_error : float
        The median over the views of the kept pixels' mean, and its standard error.
    frame_variance, smooth_variance : float
        The kept pixels' variance about their view's mean, and about their view's surface.
    """
    p = np.asarray(projections, dtype=np.float64)
    n = len(p)
    mask = frame_mask(p.shape[-2:], frame_fraction)
    full_basis = quadratic_basis(p.shape[-2:])  # (6, H, W)
    basis = full_basis[:, mask].T  # (F, 6)
    values = p[:, mask]  # (N, F)
    keep = np.ones_like(values, dtype=bool)
    for _ in range(max_rounds):
        coef = masked_least_squares(basis, values, keep)
        residual = values - coef @ basis.T
        new_keep = residual <= CLIP_Z * noise_std
        if (new_keep == keep).all():
            break
        keep = new_keep
    kept = [values[v, keep[v]] for v in range(n)]
    means = np.array([k.mean() for k in kept])
    about_mean = np.concatenate([k - m for k, m in zip(kept, means)])
    about_surface = residual[keep]
    surfaces = np.einsum("nk,khw->nhw", coef, full_basis)
    frame_var = float(about_mean.var())
    return (
        surfaces,
        float(np.median(means)),
        float(np.sqrt(frame_var / about_mean.size)),
        frame_var,
        float(about_surface.var()),
    )


def detector_floor(projections: np.ndarray, frame_fraction: float = 0.08) -> tuple[float, float, float]:
    """The level the projections sit on away from the object, and its standard error.

    Read from the outer frame of every view (``frame_fraction`` of each side, at least one
    pixel), where a tilt series of an isolated particle holds only background: the median over
    the views of each view's frame mean (the median, so the odd view with an atom column at its
    edge does not lift it; the mean within a view, because a trimmed mean or median of counts
    of about one electron is biased: 0.88 for the aSi-208 data's mean of 1.00) and its standard
    error ``std / sqrt(n)`` over all frame pixels.  A floor many standard errors from zero is a
    detector offset or a uniform background (the peer's aSi-208 counts sit on 1.0 count at
    every dose); simulated data with zero-mean noise read zero within about one standard error.

    Returns
    -------
    floor, standard_error : float
        In the projections' units.
    frame_variance : float
        The frame pixels' variance about their view's mean: about the noise variance at the
        floor when the frame is empty background, far more when the object reaches it.
    """
    p = np.asarray(projections, dtype=np.float64)
    frames = p[:, frame_mask(p.shape[-2:], frame_fraction)]
    spread = float((frames - frames.mean(axis=1, keepdims=True)).var())
    return float(np.median(frames.mean(axis=1))), float(np.sqrt(spread / frames.size)), spread
