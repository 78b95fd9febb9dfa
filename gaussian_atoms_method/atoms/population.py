"""How far a fit's widths and masses stray from their population: the precision they add to a
position's statement.

A least-squares fit with every atom's width and amplitude free would place bonded neighbours as
loosely as their information allows with all five parameters of each re-fitted.  The fit does
not use that freedom: its widths and masses stay near the population's (started there, moved at
a rate the positions' convergence stops long before they wander).  On 7,000 carbon atoms in phase
images at 2,000 e/Å² (neighbours 1.45 Å apart) the fitted widths scatter 5% and the log masses 0.15
about their medians, where their statements with everything free read 17.5% and 0.56; the
positions erred 10.3 / 8.4 / 10.3 pm (x, y, z), the information with every parameter free states
18.7 / 16.6 / 21.6 pm, with the widths and masses held 11.6 / 10.5 / 14.2 pm. The population is
the prior that describes this: each Gaussian's (log width, log amplitude) as a draw from the
reported atoms' own robust spread, its precision added to each atom's width and amplitude rows
(:func:`population_precision`) before the covariance is read.  Where the atoms are isolated the
positions do not couple to the widths and masses, and where the fitted masses scatter more than
their statements (elements, misfit: 2,000 Ni-Pd-Pt atoms through ADF, log masses 0.04-0.16 about
each element against 0.02-0.10 stated), the population is wider than the information and adds
little; several elements make one population as wide as they lie apart, so it adds less still.
"""

from __future__ import annotations

import numpy as np
import torch

from gaussian_atoms_method.physics.noise import MAD_TO_STD

LEAST_SPREAD = 1e-3
"""The least spread of a log width or log amplitude read (0.1%): Gaussians that all hold one
width (a fit that never moved them) would otherwise give an infinite precision; at this one
they are held, the information still finite (numerical, not a physical threshold)."""


def population_spread(sigmas_A: np.ndarray, amplitudes: np.ndarray) -> np.ndarray:
    """(2, 2) the robust covariance of ``(log sigma, log q)`` over the Gaussians given: each
    scale the median absolute deviation (times :data:`MAD_TO_STD`, at least
    :data:`LEAST_SPREAD`), their correlation the
    correlation of the two scaled deviations clipped at 3 (so outliers neither widen nor tilt it).

    >>> rng = np.random.default_rng(0)
    >>> s = np.exp(rng.normal(0.0, 0.05, 20000)); q = np.exp(rng.normal(0.0, 0.2, 20000)) / s**3
    >>> np.round(np.sqrt(np.diag(population_spread(s, q))), 2).tolist()
    [0.05, 0.25]
    """
    logs = np.log(np.vstack([np.asarray(sigmas_A, np.float64).ravel(), np.asarray(amplitudes, np.float64).ravel()]))
    centre = np.median(logs, axis=1, keepdims=True)
    scale = np.maximum(MAD_TO_STD * np.median(np.abs(logs - centre), axis=1), LEAST_SPREAD)
    scaled = np.clip((logs - centre) / scale[:, None], -3.0, 3.0)
    varied = logs.shape[1] > 2 and np.all(scaled.std(axis=1) > 0)
    rho = float(np.clip(np.corrcoef(scaled)[0, 1], -0.99, 0.99)) if varied else 0.0
    return np.array([[scale[0] ** 2, rho * scale[0] * scale[1]], [rho * scale[0] * scale[1], scale[1] ** 2]])


def population_precision(sigmas_A: np.ndarray, amplitudes: np.ndarray, spread: np.ndarray) -> np.ndarray:
    """(N, 2, 2) each Gaussian's prior precision on its ``(sigma, q)`` (1/Å², 1/q², 1/(Å q)):
    the population's ``spread`` of ``(log sigma, log q)`` (:func:`population_spread`) carried to
    the Gaussian's own width and amplitude, ``J^T spread^-1 J`` with ``J = diag(1/sigma, 1/q)``.

    >>> p = population_precision(np.array([0.5]), np.array([2.0]), np.diag([0.1**2, 0.2**2]))
    >>> np.round(p[0], 6).tolist()  # 1 / (0.1 * 0.5)^2, 1 / (0.2 * 2)^2
    [[400.0, 0.0], [0.0, 6.25]]
    """
    inverse = np.linalg.inv(np.asarray(spread, np.float64))
    jacobian = np.zeros((len(sigmas_A), 2, 2))
    jacobian[:, 0, 0] = 1.0 / np.asarray(sigmas_A, np.float64)
    jacobian[:, 1, 1] = 1.0 / np.asarray(amplitudes, np.float64)
    return jacobian @ inverse @ jacobian


def reported_population(sigmas_A: np.ndarray, amplitudes: np.ndarray, reported: np.ndarray) -> np.ndarray | None:
    """(N, 2, 2) the prior precision of every Gaussian a run ``reported`` (N,) bool marks as one
    it may report (:func:`population_precision` of their own :func:`population_spread`), zero
    for the rest (a floor's or a non-atom's width is no atom's); None with fewer than three.

    >>> p = reported_population(np.full(4, 0.5), np.array([1.0, 1.2, 0.9, 1.1]), np.array([1, 1, 1, 0], bool))
    >>> p.shape, bool(p[3].any())
    ((4, 2, 2), False)
    """
    reported = np.asarray(reported, bool)
    if reported.sum() < 3:
        return None
    sigmas_A, amplitudes = np.asarray(sigmas_A, np.float64), np.asarray(amplitudes, np.float64)
    spread = population_spread(sigmas_A[reported], amplitudes[reported])
    return population_precision(sigmas_A, amplitudes, spread) * reported[:, None, None]


def with_prior(info, prior):
    """``info`` (B, 5k, 5k) tensor, each set's information over its k atoms' (x, y, z, sigma, q),
    plus ``prior`` (B, k, 2, 2) on each atom's (sigma, q) rows: a new tensor.

    >>> out = with_prior(torch.zeros(1, 10, 10), torch.ones(1, 2, 2, 2))
    >>> torch.nonzero(out[0]).tolist()[:4]
    [[3, 3], [3, 4], [4, 3], [4, 4]]
    """
    out = info.clone()
    k = prior.shape[1]
    first = 5 * torch.arange(k, device=info.device) + 3
    for a in range(2):
        for b in range(2):
            out[:, first + a, first + b] += prior[:, :, a, b]
    return out
