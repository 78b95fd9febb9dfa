"""The data term: how far predicted projections are from measured ones, for the noise measured.

Four terms, each the negative log-likelihood (up to constants and scale) of one noise model
(:mod:`.noise`), or a robust version of one:

* ``"l1"``: mean absolute residual, the paper's term; the likelihood of Laplace noise and, for
  additive Gaussian noise, a median-type fit that shrugs off the odd outlier pixel at pi/2 the
  least-squares variance (:mod:`gaussian_atoms_method.atoms.uncertainty`);
* ``"l2"``: mean squared residual, the likelihood of additive Gaussian noise;
* ``"huber"``: least squares for residuals within :data:`HUBER_K` noise standard deviations,
  L1 beyond (Huber's M-estimator), divided by the corner so that its gradient is L1's
  outside it: 95% of least squares' efficiency under Gaussian noise where L1 has 64%, and the
  model's misfit, which Gaussian noise does not explain, pulls no harder than under L1;
* ``"poisson"``: the Poisson likelihood of counts, ``lambda - y log lambda`` with
  ``lambda = (m + c) / gain`` and ``y = (measured + c) / gain``: counts in units of the
  measured gain, shifted by ``c = read_var / gain`` so that a Gaussian read-out noise of
  variance ``read_var`` is carried as that many extra counts (the shifted-Poisson
  approximation of Poisson-Gaussian noise).  Its gradient is the residual over the variance
  ``read_var + gain m``: each pixel weighted by its own noise.  An L1 or L2 fit weights every
  pixel alike, so at low dose the bright background pixels' noise drowns the atoms.

:func:`choose_data_term` picks one from the measured noise: Poisson where the variance grows
with the signal significantly, Huber's where it is additive.  Why not least squares, the
additive noise's likelihood: at high dose the residual is the model's misfit (a Gaussian atom
against the Lobato potential), not noise, and least squares chases it, losing atoms and
precision.  Why not L1, the paper's term: at low dose it wastes a third of the data's
information (its variance is pi/2 least squares'), and weak atoms go without a Gaussian.
Huber's keeps both (docs/results.md).
No nerfstudio import.
"""

from __future__ import annotations

import torch

DATA_TERMS = ("l1", "l2", "huber", "poisson")
HUBER_K = 1.345
"""The Huber term's corner, in standard deviations of the noise: quadratic within, linear
beyond.  1.345 is Huber's value for 95% of least squares' efficiency under Gaussian noise
(L1 has 64%); residuals beyond it come from the model's misfit (a Gaussian atom against the
real potential's sharper core and longer tails, visible where the noise is low), which it
weighs as L1 does."""
HUBER_EFFICIENCY = 0.95
"""Least squares' variance over the Huber estimator's at :data:`HUBER_K`, under Gaussian noise."""
MIN_COUNTS = 1e-3
"""Floor of the Poisson rate, in counts, inside the logarithm only: keeps the term finite
where a prediction touches zero (a thousandth of a count changes no fit of real data)."""


MAX_PEAK_COUNTS = 1e4
"""Above this many counts at the brightest pixels the Poisson noise is under 1% of the signal:
below what interpolation, probe and model errors leave, so the data term no longer matters and
a "gain" read from such data is those errors' growth with the signal (noiseless test series
read 3e-4 per count), not shot noise."""


def choose_data_term(noise, peak: float | None = None) -> str:
    """``"poisson"`` when the noise model's gain (the variance's growth with the signal) is
    significant (:func:`.noise.fit_noise_model` zeroes it below 3 standard errors) and the
    brightest pixels (``peak``, when given) hold at most :data:`MAX_PEAK_COUNTS` counts, else
    ``"huber"`` (module docstring)."""
    if noise is None or not noise.gain > 0:
        return "huber"
    return "poisson" if peak is None or peak / noise.gain <= MAX_PEAK_COUNTS else "huber"


def data_term(
    predicted: torch.Tensor, measured: torch.Tensor, kind: str, gain: float = 1.0, read_var: float = 0.0
) -> torch.Tensor:
    """Mean over pixels of the data term ``kind`` (module docstring).

    Parameters
    ----------
    predicted, measured : tensors of one shape
        Projections in the same units (``gain`` and ``read_var`` in those units too).
    kind : {"l1", "l2", "poisson"}
    gain : float
        Projection units per count (``"poisson"`` only).
    read_var : float
        Variance of the additive part of the noise (``"poisson"`` only).
    """
    residual = predicted - measured
    if kind == "l1":
        return residual.abs().mean()
    if kind == "l2":
        return residual.square().mean()
    if kind == "huber":
        # Divided by the corner: the gradient is r / corner inside, sign(r) beyond (as L1's).
        # With a = min(|r|, corner), a (|r| - a / 2) / corner is r^2 / (2 corner) inside and
        # |r| - corner / 2 beyond, in five elementwise operations (a where() costs both branches).
        if gain > 0:
            corner = HUBER_K * torch.sqrt((read_var + gain * measured.clamp_min(0.0)).clamp_min(1e-30))
        else:
            corner = HUBER_K * max(read_var, 1e-30) ** 0.5
        size = residual.abs()
        inner = size.clamp(max=corner)
        return (inner * (size - 0.5 * inner) / corner).mean()
    if kind == "poisson":
        if not gain > 0:
            raise ValueError(f"the Poisson data term needs a positive gain, got {gain}")
        shift = read_var / gain
        rate = (predicted + shift) / gain
        counts = (measured + shift) / gain
        # Subtracting counts (log counts) - counts makes the term zero at a perfect fit (the
        # deviance / 2) without changing its gradient: about one half per pixel at the noise.
        safe = counts.clamp_min(MIN_COUNTS)
        return (rate - counts - counts * (torch.log(rate.clamp_min(MIN_COUNTS)) - torch.log(safe))).mean()
    raise ValueError(f"data term must be one of {DATA_TERMS}, got {kind!r}")
