"""The data term chosen from the noise (physics/data_terms.py) and the noise read before any fit
(physics/noise.noise_from_projections, detector_floor)."""

import numpy as np
import pytest
import torch

from gaussian_atoms_method.physics.data_terms import choose_data_term, data_term
from gaussian_atoms_method.physics.detector_floor import detector_floor
from gaussian_atoms_method.physics.noise import NoiseModel, noise_from_projections


def test_poisson_term_weights_each_pixel_by_its_variance():
    """The Poisson term's gradient is (m - y) / (gain (m + c)) per pixel (c = read_var / gain): the
    residual over the pixel's variance read_var + gain m, up to the mean's 1/n and the gain; zero
    at a perfect fit (float64)."""
    rng = np.random.default_rng(0)
    measured = torch.as_tensor(rng.uniform(0.5, 20.0, 200))
    predicted = (measured * torch.as_tensor(rng.uniform(0.8, 1.2, 200))).requires_grad_(True)
    gain, read_var = 2.0, 3.0
    data_term(predicted, measured, "poisson", gain, read_var).backward()
    expected = (predicted.detach() - measured) / (read_var + gain * predicted.detach()) / len(measured)
    torch.testing.assert_close(predicted.grad, expected, rtol=1e-9, atol=1e-15)
    assert float(data_term(measured, measured, "poisson", gain, read_var)) == pytest.approx(0.0, abs=1e-12)
    r = predicted.detach() - measured
    assert float(data_term(predicted.detach(), measured, "l1")) == pytest.approx(float(r.abs().mean()))
    assert float(data_term(predicted.detach(), measured, "l2")) == pytest.approx(float(r.square().mean()))
    with pytest.raises(ValueError, match="data term"):
        data_term(predicted, measured, "cauchy")


def test_poisson_fit_of_counts_is_unbiased_where_l1_is_not():
    """A constant fitted to Poisson counts of mean 1.3: the Poisson term's minimum is the sample
    mean (the maximum-likelihood rate); the L1 minimum is the median, 1 count: 23% low, the bias
    that let faint atoms fade in L1 fits of low-dose counts."""
    counts = torch.as_tensor(np.random.default_rng(1).poisson(1.3, 20000).astype(np.float64))
    levels = torch.linspace(0.5, 2.0, 1501, dtype=torch.float64)
    poisson = torch.stack([data_term(torch.full_like(counts, float(v)), counts, "poisson", 1.0) for v in levels])
    l1 = torch.stack([data_term(torch.full_like(counts, float(v)), counts, "l1") for v in levels])
    assert float(levels[poisson.argmin()]) == pytest.approx(float(counts.mean()), abs=0.002)
    assert float(levels[l1.argmin()]) == pytest.approx(1.0, abs=0.002)


def _sphere_series(noise):
    from gaussian_atoms_method.harness.simulate import parse_tilts, simulate_gaussian_tilt_series, spherical_particle

    return simulate_gaussian_tilt_series(
        spherical_particle("Au", radius_A=6.0), parse_tilts("limited")[::4], noise_std=noise, seed=3
    )


def test_noise_read_before_the_fit_tells_counts_from_additive_noise():
    """Gaussian noise of variance 400 on a simulated particle reads additive, its variance within
    5%, and the term chosen is Huber's; the same particle as Poisson counts (peak 40 counts, on a floor
    of one count) reads Poisson, gain within 20% of one count, and the term is Poisson."""
    sim = _sphere_series(20.0)
    additive = noise_from_projections(sim.projections)
    assert additive.kind == "additive" and additive.read_var == pytest.approx(400.0, rel=0.05)
    assert choose_data_term(additive, float(sim.projections.max())) == "huber"
    clean = _sphere_series(0.0).projections
    counts = np.random.default_rng(4).poisson(1.0 + 40.0 * clean / clean.max()).astype(np.float64)
    poisson = noise_from_projections(counts)
    assert poisson.gain == pytest.approx(1.0, rel=0.2) and choose_data_term(poisson, float(counts.max())) == "poisson"
    # A "gain" from data with tens of thousands of counts per pixel is not shot noise: additive.
    assert choose_data_term(NoiseModel(0.0, 1e-4), 10.0) == "huber"


def test_detector_floor_finds_an_offset_and_not_an_empty_frame():
    """Counts on a floor of one count: the frame reads 1.0 within 2 standard errors of its mean and
    as flat as the noise; zero-mean noise reads zero within 4 standard errors."""
    clean = _sphere_series(0.0).projections
    counts = np.random.default_rng(5).poisson(1.0 + 40.0 * clean / clean.max()).astype(np.float64)
    floor, se, frame_var = detector_floor(counts)
    assert abs(floor - 1.0) < 2 * se + 0.01 and frame_var == pytest.approx(1.0, rel=0.1)
    floor, se, _ = detector_floor(_sphere_series(20.0).projections)
    assert abs(floor) < 4 * se


def test_huber_term_is_least_squares_within_its_corner_and_l1_beyond():
    """Residuals within HUBER_K noise standard deviations pull as least squares (gradient r over
    the corner), beyond it as L1 (gradient the sign), so an atom's fit weighs noise
    efficiently and the model's misfit robustly; the corner follows the noise (read variance
    plus gain times the level)."""
    from gaussian_atoms_method.physics.data_terms import HUBER_K

    read_var, gain = 4.0, 0.5
    measured = torch.tensor([0.0, 0.0, 10.0, 10.0], dtype=torch.float64)
    corner = HUBER_K * torch.sqrt(read_var + gain * measured)
    residual = torch.tensor([0.5, 10.0, 1.0, -30.0], dtype=torch.float64)  # within, beyond, within, beyond
    predicted = (measured + residual).requires_grad_()
    value = data_term(predicted, measured, "huber", gain, read_var)
    value.backward()
    expected = torch.tensor([0.5 / corner[0], 1.0, 1.0 / corner[2], -1.0], dtype=torch.float64) / 4
    torch.testing.assert_close(predicted.grad, expected, rtol=1e-12, atol=0.0)
    parts = torch.where(residual.abs() <= corner, 0.5 * residual**2 / corner, residual.abs() - 0.5 * corner)
    assert float(value.detach()) == pytest.approx(float(parts.mean()), rel=1e-12)
