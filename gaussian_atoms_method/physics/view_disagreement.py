"""The views' own noise at the atoms' scale, read from what neighbouring views do not share.

Before a fit the noise is read from neighbouring pixels and, where the views' spectrum holds a
band no atom reaches, carried to the atoms' scale through it (:mod:`.noise_spectrum`).  Denoised
or blurred views hold no such band: their spectrum falls all the way to the Nyquist frequency (the
measured Ta film's views fall as a blur of 1.1 px), and what neighbouring pixels show is a small
part of the noise an atom sees (a denoiser takes the high frequencies and leaves the low ones).

After a fit the residual holds that noise and whatever the fit could not explain.  The two differ
in one way a tilt series can see: the object is one for every view, so a misfit of the atoms
(a profile the Gaussians lack, an atom missed or misplaced) changes little between views a few
degrees apart, while the noise of each view is its own.  Seen over an atom (each residual view,
whitened by the noise model, filtered by the atom's Gaussian), half the mean squared difference
between two views ``D/2`` is the noise variance plus what the misfit changed between them.  A
point at depth ``z'`` along a view's beam moves by ``z' d`` between views ``d`` apart, so the
misfit's change grows with ``d``: as ``d^2`` where every image moves by less than its width, as
``d`` where most move by about their width or more (a film's edges at high tilt: measured on a
constructed misfit of 80 blobs within 30 px of the axis, 2.6° apart, ``D/2`` grew by equal steps
over six separations).  So ``D/2`` over the pairs of each view and its nearest neighbours in beam
direction, at the nearest two separations, is fitted by ``s^2 + a d`` and the intercept ``s^2``
is the noise over an atom (:func:`view_disagreement`): in the first case it reads less than the
noise by ``2 a' d^2`` (``a'`` the quadratic's coefficient), in the second the noise.

What no separation resolves reads as noise: a misfit that has changed wholly between the
nearest views.  On the Ta film's sub-area 23 (46 views about 2.5° apart) ``D/2`` is 0.72 of the
residual's variance over an atom at the nearest views and 0.94 at the next: the noise reads 0.50
of it, the residual 1.41 times the noise in standard deviation; on a simulated Au particle with
white noise it reads 0.96 of the noise model's (which is right there to 1%).

A replica's noise is known: :func:`known_noise_over_atom` reads the noise drawn into its views
the same way, the truth a run's reading is checked against.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gaussian_atoms_method.physics.noise import MAD_TO_STD, gaussian_taps

NEIGHBOURS = 4
"""Each view is paired with this many nearest views by beam direction: on a single-axis series
the next and the one after on either side, the two separations the fit of ``s^2 + a d`` reads."""

SEPARATIONS_READ = 2.5
"""Pairs up to this many times the views' typical nearest separation are read: on a single-axis
series of even steps the nearest and the next (a view at an end of the series also has
neighbours three and four steps away on its one side, where the misfit's change is no longer
near its first term)."""


NEAREST_CLASS = 1.5
"""The nearest views' difference, which bounds the noise read, is that of every pair closer than
this many typical separations: each view with its nearest neighbours, half-way to the next
separation (the tilt steps of a measured series vary: the Ta film's sub-area 23 holds steps of
1.6-3.4°).  Bounded by the single closest pair instead, the reading rested on one pair's scatter:
on a replica of sub-area 23 it read 0.90 of the noise drawn into the views, 0.98 with the class."""


@dataclass(frozen=True)
class ViewDisagreement:
    """``noise_excess``: the variance over an atom that neighbouring views do not share, in units
    of the noise model's (1 where the model describes the views' noise); ``residual_excess``: the
    residual's whole variance over an atom in the same units; ``pairs``: the view pairs read."""

    noise_excess: float
    residual_excess: float
    pairs: int

    @property
    def structure_share(self) -> float:
        """The share of the residual's variance over an atom that views share: what no noise
        explains (a misfit of the atoms)."""
        return max(0.0, 1.0 - self.noise_excess / max(self.residual_excess, 1e-300))


def _robust_variance(values: np.ndarray) -> float:
    """The normalised median absolute deviation squared (atoms missed by a fit leave tails)."""
    return float((MAD_TO_STD * np.median(np.abs(values - np.median(values)))) ** 2)


def _array(x) -> np.ndarray:
    return np.asarray(x.detach().cpu() if hasattr(x, "detach") else x, dtype=np.float64)


def _over_atom(images, variance, sigma_px: float) -> tuple[np.ndarray, float] | None:
    """(V, H, W) ``images`` whitened by ``variance`` and filtered by the atom's Gaussian of
    ``sigma_px``, away from the edges where the filter sees padding, and the variance white noise
    of unit variance keeps through the filter; None for views too small to filter."""
    from scipy import ndimage

    w = _array(images)
    radius = int(np.ceil(4.0 * sigma_px))
    if min(w.shape[-2:]) <= 2 * radius + 4:
        return None
    w = w / np.sqrt(np.maximum(_array(variance), 1e-300))
    g2 = float((gaussian_taps(sigma_px, radius) ** 2).sum()) ** 2
    filtered = ndimage.gaussian_filter(w, (0, sigma_px, sigma_px), mode="constant", truncate=radius / sigma_px)
    return filtered[:, radius:-radius, radius:-radius], g2


def known_noise_over_atom(noise, variance, sigma_px: float) -> float | None:
    """The variance over an atom of ``sigma_px`` of a known (V, H, W) ``noise`` field (a
    replica's own), in units of the (V, H, W) or broadcastable ``variance`` model: the truth
    :func:`view_disagreement`'s ``noise_excess`` reads; None for views too small to filter.

    >>> rng = np.random.default_rng(0)
    >>> round(known_noise_over_atom(2 * rng.standard_normal((8, 128, 128)), np.full(1, 4.0), 1.5), 2)
    1.01
    """
    over_atom = _over_atom(noise, variance, sigma_px)
    if over_atom is None:
        return None
    filtered, g2 = over_atom
    return float(np.mean(filtered**2)) / g2


def neighbour_pairs(beams: np.ndarray, neighbours: int = NEIGHBOURS) -> tuple[np.ndarray, np.ndarray]:
    """The pairs (P, 2) of each view with its ``neighbours`` nearest views by the angle between
    their (V, 3) ``beams``, each pair once, and their angles (P,), radians.

    >>> beams = np.c_[np.sin(np.radians([0, 3, 6, 9])), np.zeros(4), np.cos(np.radians([0, 3, 6, 9]))]
    >>> pairs, angles = neighbour_pairs(beams, 2)
    >>> pairs.tolist(), np.degrees(angles).round(1).tolist()
    ([[0, 1], [0, 2], [1, 2], [1, 3], [2, 3]], [3.0, 6.0, 3.0, 6.0, 3.0])
    """
    b = np.asarray(beams, dtype=np.float64)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    angle = np.arccos(np.clip(b @ b.T, -1.0, 1.0))
    np.fill_diagonal(angle, np.inf)
    k = min(neighbours, len(b) - 1)
    nearest = np.argsort(angle, axis=1, kind="stable")[:, :k]
    pairs = np.unique(np.sort(np.c_[np.repeat(np.arange(len(b)), k), nearest.ravel()], axis=1), axis=0)
    return pairs, angle[pairs[:, 0], pairs[:, 1]]


def view_disagreement(residuals, variance, sigma_px: float, beams: np.ndarray) -> ViewDisagreement | None:
    """The noise over an atom that neighbouring views do not share (module text).

    Parameters
    ----------
    residuals : (V, H, W) array or tensor
        Measured less predicted views.
    variance : (V, H, W) array or tensor
        The noise model's variance of each pixel, in the residuals' units squared.
    sigma_px : float
        The atoms' typical width, pixels: the scale the reading is for.
    beams : (V, 3) array
        Each view's beam direction.

    Returns
    -------
    ViewDisagreement or None
        None with fewer than three views or views too small to filter.

    Examples
    --------
    Noise the model describes reads 1; a misfit every view shares adds to the residual only:

    >>> rng = np.random.default_rng(0)
    >>> tilts = np.radians(np.arange(-45, 46, 3.0))
    >>> beams = np.c_[np.sin(tilts), np.zeros_like(tilts), np.cos(tilts)]
    >>> shared = np.broadcast_to(3 * rng.standard_normal((64, 64)), (len(tilts), 64, 64))
    >>> read = view_disagreement(rng.standard_normal((len(tilts), 64, 64)) + shared, np.ones(1), 1.5, beams)
    >>> round(read.noise_excess, 1), read.residual_excess > 5
    (1.0, True)
    """
    r = _array(residuals)
    if r.ndim != 3 or len(r) < 3:
        return None
    over_atom = _over_atom(r, variance, sigma_px)
    if over_atom is None:
        return None
    filtered, g2 = over_atom
    pairs, angles = neighbour_pairs(beams)
    step = float(np.median(np.sort(angles)[: len(r)]))  # about the views' nearest separation
    kept = angles <= SEPARATIONS_READ * step  # the nearest two separations (the ends' farther pairs left out)
    pairs, angles = pairs[kept], angles[kept]
    half_d = np.array([_robust_variance(filtered[i] - filtered[j]) / 2.0 for i, j in pairs])
    design = np.c_[np.ones(len(pairs)), angles]
    if np.ptp(angles) > 1e-9:
        intercept = float(np.linalg.lstsq(design, half_d, rcond=None)[0][0])
    else:  # one separation only: its difference is the bound
        intercept = float(half_d.mean())
    nearest = float(half_d[angles < NEAREST_CLASS * step].mean())
    noise = min(max(intercept, 0.0), nearest)  # at most what the nearest views' difference allows
    whole = _robust_variance(filtered)
    return ViewDisagreement(noise / g2, whole / g2, len(pairs))
