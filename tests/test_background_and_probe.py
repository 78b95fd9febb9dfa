"""A floor that varies within the views, read from their frames; the aberrated probe of the
harness; the noise the final stage judges in."""

import numpy as np
import pytest

from gaussian_atoms_method.harness.simulate import blur_and_noise, project_gaussian_potential, spherical_particle
from gaussian_atoms_method.physics.microscope import aberrated_probe_intensity, add_varying_floor, convolve_views
from gaussian_atoms_method.physics.noise import NoiseModel, atom_scale_excess, noise_from_projections

ANGLES = np.arange(-60.0, 61.0, 10.0)


def test_aberrated_probe_has_tails_no_gaussian_has():
    """Unit sum; a sub-Å core (a third of the intensity within 0.6 Å) but 9% beyond 2 Å, more
    than five times what a Gaussian with the same half-intensity radius holds there (0.8%)."""
    pixel = 0.34
    probe = aberrated_probe_intensity(pixel)
    assert probe.sum() == pytest.approx(1.0) and probe.min() >= 0
    c = probe.shape[0] // 2
    assert probe.shape[0] % 2 == 1 and np.unravel_index(probe.argmax(), probe.shape) == (c, c)  # centred: no shift
    point = np.zeros((1, 41, 41))
    point[0, 20, 20] = 1.0
    blurred = convolve_views(point, probe)[0]
    centroid = [(blurred.sum(axis=1 - a) * np.arange(41)).sum() / blurred.sum() for a in (0, 1)]
    np.testing.assert_allclose(centroid, [20.0, 20.0], atol=1e-6)  # a point's image stays where it is
    r = np.hypot(*np.meshgrid(np.arange(probe.shape[0]) - c, np.arange(probe.shape[1]) - c, indexing="ij")) * pixel
    assert probe[r <= 0.6].sum() > 0.3
    half = np.sort(r.ravel())[np.searchsorted(np.cumsum(probe.ravel()[np.argsort(r.ravel())]), 0.5)]
    sigma = half / np.sqrt(2 * np.log(2))  # the Gaussian holding half its intensity within `half`
    assert probe[r > 2.0].sum() > 5 * np.exp(-(2.0**2) / (2 * sigma**2))


def test_smooth_floor_is_recovered_from_the_frames():
    """A floor at 25% of a column with a 5% ramp across each view: the auto background finds it
    (the frame is not flat, but flat about its quadratic surface) and the floor plus each view's
    surface reproduce the true floor to 0.4% of its level (the noise, 1% of the level per pixel,
    averaged by a 6-term fit over each view's ~1,000 frame pixels: about 0.1% per term, up to 0.3%
    at the corners)."""
    from gaussian_atoms_method.engine.noise_reading import noise_reading
    from gaussian_atoms_method.physics.noise import measure_noise

    def read_noise(data, loss, background, noise=None):
        noise = measure_noise(data) if noise is None else noise
        return noise_reading(data, loss, background, noise)[:4]

    rng = np.random.default_rng(0)
    clean = blur_and_noise(
        project_gaussian_potential(spherical_particle("Au", radius_A=6.0), ANGLES, 0.3, 64), 0.3, 0.5, 0.0, 0
    )
    with_floor = add_varying_floor(clean, 0.25, 0.05, seed=3)
    true_floor = with_floor - clean
    data = with_floor + 0.01 * true_floor.mean() * rng.standard_normal(clean.shape)
    noise, _, floor, surfaces = read_noise(data, "auto", "auto", noise_from_projections(data))
    assert floor is not None and surfaces is not None and surfaces.shape == data.shape
    np.testing.assert_allclose(floor + surfaces, true_floor, atol=0.004 * true_floor.mean())
    # A flat floor stays a constant; no floor, no background.
    flat = clean + 0.25 * np.percentile(clean, 99.9) + 0.01 * rng.standard_normal(clean.shape)
    assert read_noise(flat, "auto", "auto")[3] is None and read_noise(flat, "auto", "auto")[2] is not None
    assert read_noise(clean + 0.01 * rng.standard_normal(clean.shape), "auto", "auto")[2:] == (None, None)


def test_atom_scale_excess_is_one_for_the_noise_and_more_for_a_misfit():
    """White noise of the stated variance reads 1 (to 3%); the same noise plus an atom-sized
    misfit everywhere (what a forward model that lacks the probe's tails leaves) reads several."""
    rng = np.random.default_rng(1)
    noise = rng.standard_normal((20, 96, 96))
    assert atom_scale_excess(noise, np.ones_like(noise), 2.0) == pytest.approx(1.0, abs=0.03)
    misfit = convolve_views(rng.standard_normal(noise.shape), np.outer(*[np.exp(-(np.arange(-8, 9) ** 2) / 8.0)] * 2))
    assert atom_scale_excess(noise + misfit / misfit.std(), np.ones_like(noise), 2.0) > 3.0
    counts_mean = rng.uniform(0.5, 3.0, noise.shape)  # Poisson counts judged by their own model
    assert atom_scale_excess(
        rng.poisson(counts_mean) - counts_mean, NoiseModel(0.0, 1.0).variance(counts_mean), 2.0
    ) == pytest.approx(1.0, abs=0.05)
