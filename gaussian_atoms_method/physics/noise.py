"""The pixel noise of a tilt series, read from the data: additive, Poisson-like, or both.

Simulations add Gaussian noise of one variance everywhere; electron counts (the peer's aSi-208
data) have a variance that grows with the mean; ptychographic phase images are closer to
additive.  Given residuals ``r = measured - predicted`` and the prediction ``m`` (after a fit,
or against any smooth estimate of the mean), the variance-mean relation

    Var[r | m] = read_var + gain * max(m - offset, 0) + misfit * max(m - offset, 0)^2

tells them apart: ``gain`` is about 0 for additive noise and the number of projection units
per count for Poisson counts (1 for raw counts).  The quadratic term takes up what grows in
proportion to the signal itself, a fit's relative error (an atom slightly off in position or
width leaves residuals proportional to its peak): without it, on additive data fitted closely,
the slope of the peaks' misfit reads as a Poisson gain.  Each bin of ``m`` gives a robust
variance (the normalised median absolute deviation squared, so atoms the fit misses do not inflate it);
a weighted straight line through the bins gives ``read_var`` and ``gain`` with their standard
errors, and the Poisson part counts only when its slope is significant (``z_min`` standard
errors; 3: a one-in-700 false alarm for Gaussian errors).

This module is the measurement only: what the fit does with it (the data term, thresholds in
units of the noise) is density control's and the model's.  Arrays are read with numpy on a
machine without a GPU; with one (or given tensors on one) the filters, sorts and medians run in
torch there (:func:`~gaussian_atoms_method.physics.devices.work_device`), since a host's sorts
over millions of pixels are slow beside a GPU's.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from gaussian_atoms_method.physics.devices import HOST, gpu, work_device  # noqa: F401  (HOST: read from here too)

MAD_TO_STD = 1.4826
"""Standard deviation of a normal distribution per median absolute deviation."""


@dataclass(frozen=True)
class NoiseModel:
    """``Var = read_var + gain * x + misfit * x^2``, ``x = max(mean, least_mean, offset) - offset``,
    in projection units (squared)."""

    read_var: float
    gain: float
    offset: float = 0.0
    read_var_se: float = 0.0
    gain_se: float = 0.0
    misfit: float = 0.0
    """Variance per squared signal: the fit's relative error, not noise."""
    least_mean: float = -np.inf
    """The lowest level the reading saw (its lowest bin's mean less half the step to the next):
    below it the variance is held at that level's.  The line is read over the levels the data
    hold; a series with no dark pixel (a support film under every view) fits its intercept by
    extrapolation, and a Ta film's replica under 30 Å of carbon read 0 for a true 40.5, which
    put the variance of a pixel the Gaussians leave dark at zero."""
    correlation: float = 1.0
    """The noise the atoms see over what neighbouring pixels show, where the views' noise is
    correlated (interpolated or filtered views, :mod:`.noise_spectrum`); every variance term
    above is already multiplied by it (a pixel's own: :meth:`pixel_variance`)."""
    correlation_read: bool = True
    """False where the views' spectrum holds no band beyond the atoms to read the correlation in
    (blurred or denoised views): the noise may be correlated, and is taken as it was read."""
    correlation_from: str = "spectrum"
    """Where :attr:`correlation` was read: "spectrum", the views' band beyond the atoms before the
    fit; "views", what neighbouring views do not share of the fit's residual
    (:mod:`.view_disagreement`), read after the fit where the spectrum could not."""

    def scaled(self, factor: float) -> "NoiseModel":
        """The same noise for the data multiplied by ``factor`` (the misfit, a relative
        variance, is unchanged)."""
        f = float(factor)
        return dataclasses.replace(
            self,
            read_var=self.read_var * f * f,
            gain=self.gain * f,
            offset=self.offset * f,
            read_var_se=self.read_var_se * f * f,
            gain_se=self.gain_se * f,
            least_mean=self.least_mean * f if f > 0 else -np.inf,
        )

    def pixel_variance(self, mean):
        """A pixel's own variance at ``mean`` (:meth:`variance` less the :attr:`correlation`)."""
        return self.variance(mean) / self.correlation

    @property
    def kind(self) -> str:
        """ "additive", "poisson" or "mixed": which terms are significantly above zero."""
        poisson = self.gain > 0
        additive = self.read_var > 3 * self.read_var_se
        return "mixed" if poisson and additive else ("poisson" if poisson else "additive")

    def variance(self, mean):
        """Expected variance of a pixel whose noise-free value is ``mean`` (an array, or a tensor:
        then float64 on its device)."""
        least = max(self.least_mean, self.offset)
        if not isinstance(mean, np.ndarray) and hasattr(mean, "clamp_min"):  # a tensor
            x = mean.double().clamp_min(least) - self.offset
        else:
            x = np.maximum(np.asarray(mean, dtype=np.float64), least) - self.offset
        return self.read_var + self.gain * x + self.misfit * x**2


MIN_SIDE_PX = 5
"""The smallest image side the noise reading takes: its filters compare each pixel with a 5 x 5
neighbourhood."""


def atom_scale_excess(residuals: np.ndarray, variance: np.ndarray, sigma_px: float, device=None) -> float:
    """How much more the (V, H, W) ``residuals`` vary over an atom than the noise model says:
    ``Var(g * (r / sqrt(v))) / sum g^2`` for ``g`` the Gaussian of ``sigma_px`` and ``v`` the
    model's per-pixel ``variance`` (a robust variance, 1.4826 MAD squared, of the filtered field
    away from the edges).

    1 for noise the model describes (white noise of the stated variance reads 1.00-1.03 at
    1-5 pixels); what a fit leaves on real data is larger and correlated over an atom
    (denoised projections, a probe's tails, the model's misfit), and every chi-square over
    pixels that treats it as the model's noise overstates a difference at the atom's scale by
    this factor.  ``device``: where it runs (default :func:`~gaussian_atoms_method.physics.devices.work_device`)."""
    from scipy import ndimage

    radius = int(np.ceil(4.0 * sigma_px))
    device = work_device(residuals, device)
    if device is not None:
        return _atom_scale_excess_torch(residuals, variance, sigma_px, radius, device)
    w = np.asarray(residuals, dtype=np.float64) / np.sqrt(np.maximum(np.asarray(variance, dtype=np.float64), 1e-300))
    w = w.reshape((-1,) + w.shape[-2:])
    impulse = np.zeros((2 * radius + 1,) * 2)
    impulse[radius, radius] = 1.0
    g2 = float((ndimage.gaussian_filter(impulse, sigma_px, mode="constant", truncate=radius / sigma_px) ** 2).sum())
    filtered = ndimage.gaussian_filter(w, (0, sigma_px, sigma_px), mode="constant", truncate=radius / sigma_px)
    if min(w.shape[-2:]) > 2 * radius + 4:  # away from the edges, where the filter sees the padding
        filtered = filtered[:, radius:-radius, radius:-radius]
    spread = MAD_TO_STD * np.median(np.abs(filtered - np.median(filtered)))
    return float(spread**2 / g2)


def _atom_scale_excess_torch(residuals, variance, sigma_px: float, radius: int, device) -> float:
    """:func:`atom_scale_excess` in torch on ``device``: the same sampled Gaussian, zero outside
    the images (scipy's ``constant`` mode), the same crop and robust spread."""
    import torch

    w = _as_float64(residuals, device) / _as_float64(variance, device).clamp_min(1e-300).sqrt()
    w = w.reshape((-1,) + tuple(w.shape[-2:]))
    taps = gaussian_taps(sigma_px, radius)
    g2 = float((taps**2).sum()) ** 2  # the squared filter's sum: the impulse's response is the kernel's outer product
    padded = torch.nn.functional.pad(w, (radius, radius, radius, radius))
    filtered = separable_correlate(padded, taps, taps)
    if min(w.shape[-2:]) > 2 * radius + 4:
        filtered = filtered[:, radius:-radius, radius:-radius]
    spread = MAD_TO_STD * median_on_device((filtered - median_on_device(filtered.reshape(-1))).abs().reshape(-1))
    return float(spread**2 / g2)


def gaussian_taps(sigma_px: float, radius: int) -> np.ndarray:
    """(2 radius + 1,) scipy's sampled Gaussian of ``sigma_px`` (``gaussian_filter`` with
    ``truncate = radius / sigma_px``), summing to one."""
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    phi = np.exp(-0.5 * x**2 / float(sigma_px) ** 2)
    return phi / phi.sum()


def separable_correlate(padded, taps_rows: np.ndarray, taps_cols: np.ndarray):
    """The valid correlation of (V, H + 2a, W + 2b) ``padded`` with the outer product of the
    (2a + 1,) ``taps_rows`` and (2b + 1,) ``taps_cols``: (V, H, W), as weighted sums of shifted
    slices (one pass per axis)."""
    h, w = padded.shape[-2] - len(taps_rows) + 1, padded.shape[-1] - len(taps_cols) + 1
    rows = sum(float(t) * padded[:, k : k + h, :] for k, t in enumerate(taps_rows))
    return sum(float(t) * rows[:, :, k : k + w] for k, t in enumerate(taps_cols))


def _as_float64(values, device):
    """``values`` (an array or tensor) as a float64 tensor on ``device``."""
    import torch

    if isinstance(values, torch.Tensor):
        return values.to(device, torch.float64)
    values = np.asarray(values, dtype=np.float64)
    return torch.as_tensor(values if values.flags.writeable else values.copy(), device=device)


def inflated(noise: NoiseModel, factor: float) -> NoiseModel:
    """``noise`` with every variance term times ``factor`` (standard errors alike)."""
    f = float(factor)
    return dataclasses.replace(
        noise,
        read_var=noise.read_var * f,
        gain=noise.gain * f,
        read_var_se=noise.read_var_se * f,
        gain_se=noise.gain_se * f,
        misfit=noise.misfit * f,
    )


def binned_variance(
    residuals: np.ndarray, predicted: np.ndarray, bins: int = 16, min_count: int = 200, robust: bool = True, device=None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Residual variance in bins of the predicted value: robust, ``(1.4826 MAD)^2``, or the
    plain sample variance (``robust=False``: for counts of a few electrons, whose residuals
    take a handful of discrete values and whose MAD is quantised, reading the variance too
    high).  The sort and the bins are read in torch on
    ``device`` (default :func:`~gaussian_atoms_method.physics.devices.work_device`: at many atoms the
    host's sort, gathers and copies are most of a reading), else with numpy.

    Returns
    -------
    centres : (B,) mean predicted value in each bin (equal-count bins, B <= ``bins``)
    variances : (B,) (1.4826 * MAD)^2 of the residuals in the bin
    counts : (B,) pixels per bin (bins with fewer than ``min_count`` are dropped)
    """
    device = work_device(residuals, device)
    if device is not None:
        return _binned_variance_torch(residuals, predicted, bins, min_count, robust, device)
    r, m = as_array(residuals).ravel(), as_array(predicted).ravel()
    label, sizes = equal_count_bins(m, bins)
    order = np.argsort(label, kind="stable")  # small integers: a radix sort, the bins' members in index order
    centres, variances, counts = [], [], []
    for chunk in np.split(order, np.cumsum(sizes)[:-1]):
        if len(chunk) < min_count:
            continue
        rc = r[chunk]
        centres.append(m[chunk].mean())
        variances.append(float(np.var(rc)) if not robust else mad_std(rc, device) ** 2)
        counts.append(len(chunk))
    return np.array(centres), np.array(variances), np.array(counts)


def equal_count_bins(values: np.ndarray, bins: int) -> tuple[np.ndarray, np.ndarray]:
    """(n,) the bin of each of the (n,) ``values`` and the (bins,) bin sizes: ``np.array_split``'s
    bins of the values in stable sorted order, without the sort.  Each bin's first rank is
    selected (``np.partition``); a value below an edge lies before it, above it after, and values
    equal to an edge take their ranks in index order, as a stable sort gives them: linear time
    where the sort is n log n."""
    values = np.asarray(values)
    n = len(values)
    sizes = np.array([n // bins + 1] * (n % bins) + [n // bins] * (bins - n % bins), dtype=np.int64)
    starts = np.cumsum(sizes)[:-1]
    starts = starts[starts < n]  # more bins than values: the last ones are empty
    if len(starts) == 0:
        return np.zeros(n, dtype=np.int64), sizes
    edges = np.partition(values, starts)[starts]
    label = np.searchsorted(edges, values, side="left")  # the edges strictly below each value
    for u in np.unique(edges):  # values at an edge: the first (start - below) of them, in index order, lie before it
        equal = np.flatnonzero(values == u)
        below = np.count_nonzero(values < u)
        for start in starts[edges == u]:
            label[equal[start - below :]] += 1
    return label, sizes


def _binned_variance_torch(residuals, predicted, bins: int, min_count: int, robust: bool, device):
    """:func:`binned_variance` in torch on ``device``: the same stable order and bins
    (``np.array_split``'s sizes), each bin's mean and variance there."""
    import torch

    r, m = _as_float64(residuals, device).reshape(-1), _as_float64(predicted, device).reshape(-1)
    order = torch.sort(m, stable=True).indices
    m, r = m[order], r[order]
    n = len(m)
    sizes = [n // bins + 1] * (n % bins) + [n // bins] * (bins - n % bins)
    centres, variances, counts, start = [], [], [], 0
    for size in sizes:
        if size >= min_count:
            rc = r[start : start + size]
            centres.append(float(m[start : start + size].mean()))
            variances.append(mad_std(rc, device) ** 2 if robust else float(rc.var(unbiased=False)))
            counts.append(size)
        start += size
    return np.array(centres), np.array(variances), np.array(counts)


def median_on_device(values):
    """numpy's median of a 1D tensor (the mean of the two middle values for an even count), on
    the tensor's device: a sort, where numpy partitions on one CPU core."""
    ordered = values.sort().values
    n = len(ordered)
    return ordered[n // 2] if n % 2 else 0.5 * (ordered[n // 2 - 1] + ordered[n // 2])


def mad_std(values, device=None) -> float:
    """``1.4826 * MAD`` of the finite ``values`` (an array or a tensor).  The medians are taken
    in torch on ``device`` (default: a tensor's own device off the CPU, else a GPU where there is
    one; :func:`median_on_device`), else by numpy's median (linear time on the CPU) in one float64
    copy of ``values``, partitioned in place (three copies fewer than ``np.median``)."""
    import torch

    if device is None:
        device = values.device if isinstance(values, torch.Tensor) and values.device.type != "cpu" else gpu()
    if device is None:
        host = values.detach().numpy() if isinstance(values, torch.Tensor) else values
        v = np.array(host, dtype=np.float64).ravel()  # a copy: the medians below reorder it
        finite = np.isfinite(v)
        if not finite.all():
            v = v[finite]
        if v.size == 0:
            raise ValueError("no finite values to estimate a spread from")
        np.abs(np.subtract(v, np.median(v, overwrite_input=True), out=v), out=v)
        return float(MAD_TO_STD * np.median(v, overwrite_input=True))
    t = torch.as_tensor(values, dtype=torch.float64, device=device).reshape(-1)
    t = t[torch.isfinite(t)]
    if t.numel() == 0:
        raise ValueError("no finite values to estimate a spread from")
    return float(MAD_TO_STD * median_on_device((t - median_on_device(t)).abs()))


def _solve(matrix: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """``matrix^-1 rhs``; the least-squares solution where ``matrix`` is singular (a flat series:
    one mean in every bin makes the variance-mean design collinear)."""
    try:
        return np.linalg.solve(matrix, rhs)
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(matrix, rhs, rcond=None)[0]


def fit_noise_model(
    residuals: np.ndarray,
    predicted: np.ndarray,
    offset: float = 0.0,
    bins: int = 16,
    z_min: float = 3.0,
    robust: bool = True,
    quadratic: bool = True,
    device=None,
) -> NoiseModel:
    """Fit ``Var = read_var + gain * x + misfit * x^2`` (``x = max(m - offset, 0)``) to the
    binned robust variances.

    A bin's variance estimate has a relative standard error of about ``sqrt(2 / (0.37 n))``
    for ``n`` pixels (the MAD is 37% as efficient as the sample variance for normal data), so
    bins are weighted by ``0.37 n / (2 var^2)``.  ``gain`` is set to 0 unless it exceeds
    ``z_min`` standard errors; ``read_var`` is floored at 0.  ``quadratic=False`` leaves out
    the misfit term (before any fit there is no fit error to take up, and over the narrow
    range of means of low-dose counts, 0.8-2 counts, ``x`` and ``x^2`` are nearly collinear:
    the quadratic took the Poisson slope of the aSi-208 data at dose 8e3).  ``device``: where
    the bins are read (:func:`binned_variance`).
    """
    centres, variances, counts = binned_variance(residuals, predicted, bins, robust=robust, device=device)
    if len(centres) < 2:
        var = float(variances[0]) if len(variances) else float(np.var(as_array(residuals)))
        return NoiseModel(max(var, 0.0), 0.0, offset, least_mean=float(centres[0]) if len(centres) else -np.inf)
    x = np.maximum(centres - offset, 0.0)
    # Noiseless data (tests, simulations without noise) give zero variances: weights stay finite.
    variances = np.maximum(variances, 1e-12 * max(float(variances.max()), float(np.abs(centres).max()) ** 2, 1e-300))
    design = np.stack([np.ones_like(x), x, x**2], axis=1)[:, : min(3 if quadratic else 2, len(centres) - 1)]
    weights = 0.37 * counts / (2.0 * np.maximum(variances, 1e-300) ** 2)
    # Iterate once: weights from the fitted variances rather than the noisy bin estimates.
    for _ in range(2):
        normal = design.T @ (weights[:, None] * design)
        coef = _solve(normal, design.T @ (weights * variances))
        fitted = np.maximum(design @ coef, 1e-12 * float(variances.max()))  # squared below: no underflow to 0
        weights = 0.37 * counts / (2.0 * fitted**2)
    cov = _solve(design.T @ (weights[:, None] * design), np.eye(design.shape[1]))
    read_var, gain = float(coef[0]), float(coef[1])
    misfit = float(coef[2]) if len(coef) > 2 else 0.0
    read_se, gain_se = float(np.sqrt(cov[0, 0])), float(np.sqrt(cov[1, 1]))
    if gain < z_min * gain_se:
        gain = 0.0
    lowest = float(centres[0] - 0.5 * (centres[1] - centres[0]))  # the lowest bin's lower edge
    return NoiseModel(max(read_var, 0.0), max(gain, 0.0), offset, read_se, gain_se, max(misfit, 0.0), lowest)


IMMERKAER_KERNEL = np.outer([1.0, -2.0, 1.0], [1.0, -2.0, 1.0])
"""Product of two second differences (Immerkær, "Fast noise variance estimation", CVIU 1996):
blind to any signal up to a quadratic in each axis, so an atom's smooth peak leaves little in
it; for independent pixels of locally constant variance the filtered value has 36 times the
pixel variance (the sum of the squared weights)."""


def as_array(projections) -> np.ndarray:
    """(V, H, W) projections, a torch tensor (any device) or array-like, as a float64 array."""
    return np.asarray(
        projections.detach().cpu().double() if hasattr(projections, "detach") else projections, dtype=np.float64
    )


def measure_noise(projections, device=None) -> NoiseModel | None:
    """The noise of the (V, H, W) projections as measured (:func:`noise_from_projections`, on
    ``device``), in their units; None without data or with images under 5 x 5 pixels.  Read
    once: the start (:mod:`gaussian_atoms_method.atoms.initialise`) and the data term share it."""
    if projections is None or min(projections.shape[-2:]) < 5:
        return None
    return with_correlation(noise_from_projections(projections, device=device), projections, device)


def with_correlation(noise: NoiseModel, projections, device=None) -> NoiseModel:
    """``noise`` (read from neighbouring pixels of the (V, H, W) ``projections``) times the
    correlation of their noise where its spectrum beyond the atoms says it is correlated
    (:func:`~.noise_spectrum.noise_spectrum`: the level the atoms see over the pixels' mean
    variance), never scaled down; as it is where the noise is white, or where its band cannot be
    read (then marked ``correlation_read`` False).
    A stack shifted by random sub-pixel amounts with cubic splines reads 0.54 of its noise from
    neighbouring pixels and 1.02 with this (tests/test_noise.py)."""
    from gaussian_atoms_method.physics.noise_spectrum import noise_spectrum

    spectrum = noise_spectrum(projections, work_device(projections, device))
    if spectrum is None:
        return dataclasses.replace(noise, correlation_read=False)
    if not spectrum.correlated:
        return noise
    factor = spectrum.level / float(noise.variance(np.array([float(projections.mean())]))[0])
    return dataclasses.replace(inflated(noise, factor), correlation=factor) if factor > 1.0 else noise


def noise_from_projections(
    projections: np.ndarray, offset: float = 0.0, smoothing_px: float = 2.0, z_min: float = 3.0, device=None
) -> NoiseModel:
    """The noise model read from the projections alone, before any fit.

    Each pixel's noise is seen through :data:`IMMERKAER_KERNEL` (divided by 6 to give pixel
    units); the mean it belongs to is the projection smoothed by a Gaussian of
    ``smoothing_px`` over a ring that leaves out those 3 x 3 pixels; then
    :func:`fit_noise_model` on those pairs with plain (not MAD) variances and no misfit term.
    What an atom's peak leaves in the filter (its mixed fourth derivative: for a peak of
    2.4 px width about 1/200 of its height) is small: the demo's binned variances stay within
    3% of the 400 added, up to the atoms' peaks.  Measured: the aSi-208 counts read Poisson at all three doses, the
    Gaussian-noise demo additive (tests/test_noise.py).

    Parameters
    ----------
    projections : (N, H, W) array
        The tilt series, in any units (read_var and gain come out in the same units).
    offset : float
        Signal level below which no Poisson noise grows (a detector's dark level).
    device : torch device, optional
        Where the filters and the fit's bins run (default :func:`~gaussian_atoms_method.physics.devices.work_device`).
    """
    from scipy import ndimage

    projections = projections if hasattr(projections, "shape") else np.asarray(projections, dtype=np.float64)
    shape = tuple(projections.shape)
    if len(shape) != 3 or min(shape[1:]) < MIN_SIDE_PX:
        raise ValueError(f"need (N, H, W) projections at least {MIN_SIDE_PX} x {MIN_SIDE_PX}, got shape {shape}")
    device = work_device(projections, device)
    if device is not None:
        return _noise_from_projections_torch(projections, offset, smoothing_px, z_min, device)
    p = as_array(projections)
    filtered = ndimage.correlate(p, IMMERKAER_KERNEL[None], mode="nearest")[:, 1:-1, 1:-1] / 6.0
    # The local mean from a ring around the 3 x 3 pixels the filter reads: from the same pixels
    # it would share their noise, and binning by it would select low-noise pixels into low
    # bins (on the aSi-208 counts at dose 8e3 that faked a Poisson gain of 1.9 counts).  The
    # Gaussian smoothing less its own 3 x 3 centre (separable, so fast on large series).
    g = np.exp(-(np.arange(-1, 2) ** 2) / (2 * smoothing_px**2))
    radius = int(np.ceil(4 * smoothing_px))
    norm = np.exp(-(np.arange(-radius, radius + 1) ** 2) / (2 * smoothing_px**2)).sum()
    centre = np.outer(g, g) / norm**2  # the 3 x 3 centre of the normalised 2D Gaussian
    smooth = ndimage.gaussian_filter(p, (0, smoothing_px, smoothing_px), mode="nearest", truncate=radius / smoothing_px)
    mean = ((smooth - ndimage.correlate(p, centre[None], mode="nearest")) / (1.0 - centre.sum()))[:, 1:-1, 1:-1]
    # Plain variances: counts of a few electrons take a handful of values and defeat the MAD.
    return fit_noise_model(filtered, mean, offset=offset, z_min=z_min, robust=False, quadratic=False, device=HOST)


def _noise_from_projections_torch(projections, offset: float, smoothing_px: float, z_min: float, device) -> NoiseModel:
    """:func:`noise_from_projections` in torch on ``device``: the same filters (separable; the
    edge pixel repeated, scipy's ``nearest``) on the interior pixels it keeps."""
    import torch

    p = _as_float64(projections, device)
    radius = int(np.ceil(4 * smoothing_px))
    taps = gaussian_taps(smoothing_px, radius)
    g = taps[radius - 1 : radius + 2]  # the normalised Gaussian's 3 central taps
    second = np.array([1.0, -2.0, 1.0])
    filtered = separable_correlate(p, second, second) / 6.0
    smooth = separable_correlate(torch.nn.functional.pad(p[None], (radius,) * 4, mode="replicate")[0], taps, taps)
    mean = (smooth[:, 1:-1, 1:-1] - separable_correlate(p, g, g)) / (1.0 - g.sum() ** 2)
    return fit_noise_model(filtered, mean, offset=offset, z_min=z_min, robust=False, quadratic=False)
