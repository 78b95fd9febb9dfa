"""The pixel noise of a tilt series, read from the data: additive, Poisson-like, or both.

Simulations add Gaussian noise of one variance everywhere; electron counts (the peer's aSi-208
data) have a variance that grows with the mean; ptychographic phase images are closer to
additive.  Given residuals ``r = measured - predicted`` and the prediction ``m`` (after a fit,
or against any smooth estimate of the mean), the variance-mean relation

    Var[r | m] = read_var + gain * max(m - offset, 0) + misfit * max(m - offset, 0)^2

tells them apart: ``gain`` is about 0 for additive noise and the number of projection units
per count for Poisson counts (1 for raw counts).  The quadratic term takes up what grows in
proportion to the signal itself, a fit's relative error (an atom slightly off in position or
width leaves residuals proportional to its peak): without it, on additive data trained to
1 pm, the slope of the peaks' misfit read as a Poisson gain at 3.2 standard errors.  Each bin of ``m`` gives a robust variance
(the normalised median absolute deviation squared, so atoms the fit misses do not inflate it);
a weighted straight line through the bins gives ``read_var`` and ``gain`` with their standard
errors, and the Poisson part counts only when its slope is significant (``z_min`` standard
errors; 3: a one-in-700 false alarm for Gaussian errors).

This module is the measurement only (torch-free numpy): what the fit does with it (the data
term, thresholds in units of the noise) is density control's and the model's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MAD_TO_STD = 1.4826
"""Standard deviation of a normal distribution per median absolute deviation."""


@dataclass(frozen=True)
class NoiseModel:
    """``Var = read_var + gain * max(mean - offset, 0)`` in projection units (squared)."""

    read_var: float
    gain: float
    offset: float = 0.0
    read_var_se: float = 0.0
    gain_se: float = 0.0
    misfit: float = 0.0
    """Variance per squared signal: the fit's relative error, not noise."""

    @property
    def kind(self) -> str:
        """"additive", "poisson" or "mixed": which terms are significantly above zero."""
        poisson = self.gain > 0
        additive = self.read_var > 3 * self.read_var_se
        return "mixed" if poisson and additive else ("poisson" if poisson else "additive")

    def variance(self, mean: np.ndarray) -> np.ndarray:
        """Expected variance of a pixel whose noise-free value is ``mean``."""
        x = np.maximum(np.asarray(mean, dtype=np.float64) - self.offset, 0.0)
        return self.read_var + self.gain * x + self.misfit * x**2


def binned_variance(residuals: np.ndarray, predicted: np.ndarray, bins: int = 16, min_count: int = 200) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Robust residual variance in bins of the predicted value.

    Returns
    -------
    centres : (B,) mean predicted value in each bin (equal-count bins, B <= ``bins``)
    variances : (B,) (1.4826 * MAD)^2 of the residuals in the bin
    counts : (B,) pixels per bin (bins with fewer than ``min_count`` are dropped)
    """
    r = np.asarray(residuals, dtype=np.float64).ravel()
    m = np.asarray(predicted, dtype=np.float64).ravel()
    order = np.argsort(m, kind="stable")
    centres, variances, counts = [], [], []
    for chunk in np.array_split(order, bins):
        if len(chunk) < min_count:
            continue
        rc = r[chunk]
        mad = np.median(np.abs(rc - np.median(rc)))
        centres.append(m[chunk].mean())
        variances.append((MAD_TO_STD * mad) ** 2)
        counts.append(len(chunk))
    return np.array(centres), np.array(variances), np.array(counts)


def fit_noise_model(residuals: np.ndarray, predicted: np.ndarray, offset: float = 0.0, bins: int = 16, z_min: float = 3.0) -> NoiseModel:
    """Fit ``Var = read_var + gain * x + misfit * x^2`` (``x = max(m - offset, 0)``) to the
    binned robust variances.

    A bin's variance estimate has a relative standard error of about ``sqrt(2 / (0.37 n))``
    for ``n`` pixels (the MAD is 37% as efficient as the sample variance for normal data), so
    bins are weighted by ``0.37 n / (2 var^2)``.  ``gain`` is set to 0 unless it exceeds
    ``z_min`` standard errors; ``read_var`` is floored at 0.
    """
    centres, variances, counts = binned_variance(residuals, predicted, bins)
    if len(centres) < 2:
        var = float(variances[0]) if len(variances) else float(np.var(residuals))
        return NoiseModel(max(var, 0.0), 0.0, offset)
    x = np.maximum(centres - offset, 0.0)
    design = np.stack([np.ones_like(x), x, x**2], axis=1)[:, : min(3, len(centres) - 1)]
    weights = 0.37 * counts / (2.0 * np.maximum(variances, 1e-300) ** 2)
    # Iterate once: weights from the fitted variances rather than the noisy bin estimates.
    for _ in range(2):
        normal = design.T @ (weights[:, None] * design)
        coef = np.linalg.solve(normal, design.T @ (weights * variances))
        fitted = np.maximum(design @ coef, 1e-300)
        weights = 0.37 * counts / (2.0 * fitted**2)
    cov = np.linalg.inv(design.T @ (weights[:, None] * design))
    read_var, gain = float(coef[0]), float(coef[1])
    misfit = float(coef[2]) if len(coef) > 2 else 0.0
    read_se, gain_se = float(np.sqrt(cov[0, 0])), float(np.sqrt(cov[1, 1]))
    if gain < z_min * gain_se:
        gain = 0.0
    return NoiseModel(max(read_var, 0.0), max(gain, 0.0), offset, read_se, gain_se, max(misfit, 0.0))
