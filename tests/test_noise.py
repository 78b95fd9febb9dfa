"""The noise model read from residuals (physics/noise.py) on noise of known kind.

200,000 pixels in 16 equal-count bins: each bin's robust variance has a relative standard
error of about sqrt(2 / (0.37 * 12,500)) = 2%, the fitted line about 1%; 5% tolerances are
several standard errors."""

import dataclasses
from dataclasses import astuple

import numpy as np
import pytest

from gaussian_atoms_method.physics.noise import fit_noise_model

N = 200_000


def test_additive_noise_has_no_poisson_part():
    rng = np.random.default_rng(0)
    mean = rng.uniform(0, 100, N)
    model = fit_noise_model(rng.normal(0, 3.0, N), mean)
    assert model.kind == "additive" and model.gain == 0.0
    assert model.read_var == pytest.approx(9.0, rel=0.05)


def test_scaled_counts_are_poisson_with_their_gain():
    """Counts of mean 20-200 recorded at 0.5 units per electron: variance 0.5 x mean."""
    rng = np.random.default_rng(1)
    lam = rng.uniform(20, 200, N)
    recorded = 0.5 * rng.poisson(lam)
    model = fit_noise_model(recorded - 0.5 * lam, 0.5 * lam)
    assert model.kind == "poisson"
    assert model.gain == pytest.approx(0.5, rel=0.05)
    assert abs(model.read_var) < 3 * model.read_var_se + 0.05 * 0.5 * 20


def test_counts_with_read_noise_are_mixed():
    rng = np.random.default_rng(2)
    lam = rng.uniform(20, 200, N)
    recorded = rng.poisson(lam) + rng.normal(0, 4.0, N)
    model = fit_noise_model(recorded - lam, lam)
    assert model.kind == "mixed"
    assert model.gain == pytest.approx(1.0, rel=0.05) and model.read_var == pytest.approx(16.0, rel=0.15)
    np.testing.assert_allclose(model.variance([20.0, 200.0]), [36.0, 216.0], rtol=0.05)


def test_missed_atoms_do_not_inflate_the_noise():
    """2% of the pixels carry unexplained signal (atoms the fit missed): the robust variance
    ignores them where a plain variance would grow 30-fold."""
    rng = np.random.default_rng(3)
    mean = rng.uniform(0, 100, N)
    residuals = rng.normal(0, 3.0, N)
    residuals[rng.random(N) < 0.02] += 100.0
    model = fit_noise_model(residuals, mean)
    assert model.kind == "additive" and model.read_var == pytest.approx(9.0, rel=0.1)


def test_fit_error_proportional_to_the_signal_is_not_taken_for_poisson_noise():
    """A fit's relative error (residuals of 5% of the signal at the peaks) grows with the
    signal squared; it goes to the misfit term, and the noise stays additive."""
    rng = np.random.default_rng(4)
    mean = rng.uniform(0, 400, N)
    residuals = rng.normal(0, 20.0, N) + 0.05 * mean * rng.normal(0, 1.0, N)
    model = fit_noise_model(residuals, mean)
    assert model.kind == "additive" and model.read_var == pytest.approx(400.0, rel=0.05)
    assert model.misfit == pytest.approx(0.05**2, rel=0.15)


def test_noise_read_from_scaled_data_is_the_scaled_model():
    """The model reads the noise once, from the normalised projections (the input times
    ``data_scale``); the start uses it in the input's units (``NoiseModel.scaled``).  The reading
    is scale-equivariant (variances scale as the square, the gain and the offset as the data),
    so the scaled model equals the one read from the input itself, to float rounding; the
    misfit, a relative variance, does not change."""
    from gaussian_atoms_method.physics.noise import noise_from_projections

    rng = np.random.default_rng(3)
    lam = np.broadcast_to(np.linspace(2, 60, 48), (6, 48, 48))  # smooth: the reading's local mean follows it
    counts = 0.8 * rng.poisson(lam) + rng.normal(0, 1.5, lam.shape)
    raw = noise_from_projections(counts)
    scale = 256.0 / np.abs(counts).max()
    back = noise_from_projections(counts * scale).scaled(1.0 / scale)
    assert raw.kind == back.kind == "mixed"
    for name in ("read_var", "gain", "offset", "read_var_se", "gain_se", "misfit", "least_mean"):
        assert getattr(back, name) == pytest.approx(getattr(raw, name), rel=1e-9, abs=1e-12)
    v = np.linspace(0, 50, 11)
    np.testing.assert_allclose(raw.scaled(scale).variance(v * scale), raw.variance(v) * scale**2, rtol=1e-12)


def test_below_the_levels_it_read_the_variance_is_held_at_the_lowest():
    """Counts on a floor no pixel falls below (a support film under every view: levels 400-4000,
    read variance 40, gain 0.7, the Ta replica's): the line's intercept is an extrapolation 400
    counts below the data and may come out 0.  A pixel the model leaves dark is then not given
    zero variance: below the lowest level read the variance is that level's, within the 5%
    a bin of ~60,000 pixels reads it to; above it the line is unchanged."""
    rng = np.random.default_rng(7)
    mean = rng.uniform(400.0, 4000.0, 10**6)
    residuals = rng.normal(0.0, np.sqrt(40.0 + 0.7 * mean))
    model = fit_noise_model(residuals, mean, robust=False, quadratic=False)
    lowest = model.least_mean
    assert lowest == pytest.approx(400.0, abs=0.1 * 3600.0 / 16)  # the lowest of 16 equal-count bins' lower edge
    assert model.variance(np.array([0.0, 10.0]))[0] == pytest.approx(40.0 + 0.7 * lowest, rel=0.05)
    np.testing.assert_allclose(model.variance(np.array([0.0, lowest])), model.variance(np.array([lowest, lowest])))
    assert model.variance(np.array([3000.0]))[0] == pytest.approx(40.0 + 0.7 * 3000.0, rel=0.03)


def test_a_flat_series_reads_zero_noise_without_failing():
    """Every pixel the same (a blank or saturated series): every bin has the same mean, so the
    variance-mean design is collinear; the reading is zero noise, not a singular-matrix error."""
    from gaussian_atoms_method.physics.noise import noise_from_projections

    model = noise_from_projections(np.ones((4, 40, 40)))
    assert abs(model.read_var) < 1e-9 and abs(model.gain) < 1e-9  # the floor that keeps weights finite


def _floor_under_crowded_frame(seed: int = 0):
    """(20, 64, 64) views: a floor of 10 with a 3% ramp across each view, unit Gaussian noise and
    atoms (2D Gaussians of 1.5 px, peak 20) everywhere, the frame included: the frame's plain mean
    sits on their tails."""
    rng = np.random.default_rng(seed)
    n, h = 20, 64
    r, c = np.meshgrid(np.arange(h), np.arange(h), indexing="ij")
    views = np.empty((n, h, h))
    for v in range(n):
        ramp = 10.0 * (1.0 + 0.03 * rng.uniform(-1, 1) * (r - h / 2) / h)
        atoms = np.zeros((h, h))
        for y, x in rng.uniform(0, h, (20, 2)):
            atoms += 20.0 * np.exp(-((r - y) ** 2 + (c - x) ** 2) / (2 * 1.5**2))
        views[v] = ramp + atoms + rng.normal(0.0, 1.0, (h, h))
    return views


def test_the_floor_under_a_frame_atoms_reach_is_read_from_the_pixels_they_leave():
    from gaussian_atoms_method.physics.detector_floor import clipped_frame, detector_floor

    views = _floor_under_crowded_frame()
    plain, _, plain_var = detector_floor(views)
    surfaces, floor, se, frame_var, smooth_var = clipped_frame(views, noise_std=1.0)
    # The plain frame mean carries the atoms' tails (a deviation high, five times the noise
    # variance: not background); the clipped frame holds a floor within a quarter of a noise
    # deviation (what tails under 3 deviations add; the per-view constant the fit learns from
    # it takes up the rest), varying about its surfaces within the 1.5 noise variances that
    # call a frame background (noise_reading.FLAT_FRAME_RATIO).
    assert plain - 10.0 > 1.0 and plain_var > 5.0
    assert abs(floor - 10.0) < 0.25 and se < 0.05
    assert 0.9 < smooth_var < 1.5


@pytest.mark.parametrize("kind", ["additive", "counts"])
def test_readings_in_torch_are_numpys(kind):
    """The torch path (what a GPU run takes; here on the CPU in float64) gives numpy's readings
    to rounding: the pre-fit noise model, the binned variances (ties, as counts take few values,
    in the same stable order), the fitted model and the excess over an atom."""
    import torch

    from gaussian_atoms_method.physics.noise import atom_scale_excess, binned_variance, noise_from_projections

    rng = np.random.default_rng(5)
    rows, cols = np.arange(90)[:, None], np.arange(77)[None]
    mean = np.broadcast_to(4.0 + 30.0 * np.exp(-((rows - 45) ** 2 + (cols - 38) ** 2) / 200.0), (9, 90, 77))
    data = mean + rng.normal(0.0, 2.0, mean.shape) if kind == "additive" else rng.poisson(mean).astype(np.float64)
    residuals = data - mean
    host, device = noise_from_projections(data), noise_from_projections(torch.tensor(data), device="cpu")
    assert host.correlation_from == device.correlation_from
    for a, b in zip(astuple(host)[:-1], astuple(device)[:-1]):  # the numbers; the last field says where one was read
        assert b == pytest.approx(a, rel=1e-9, abs=1e-12)
    for a, b in zip(
        binned_variance(residuals, mean, robust=kind == "additive"),
        binned_variance(torch.tensor(residuals), torch.tensor(mean.copy()), robust=kind == "additive", device="cpu"),
    ):
        np.testing.assert_allclose(b, a, rtol=1e-12)
    for a, b in zip(
        astuple(fit_noise_model(residuals, mean))[:-1],
        astuple(fit_noise_model(torch.tensor(residuals), torch.tensor(mean.copy()), device="cpu"))[:-1],
    ):
        assert b == pytest.approx(a, rel=1e-9, abs=1e-12)
    variance = host.variance(mean)
    assert atom_scale_excess(torch.tensor(residuals), torch.tensor(variance), 1.6, device="cpu") == pytest.approx(
        atom_scale_excess(residuals, variance, 1.6), rel=1e-12
    )


def test_masked_least_squares_equals_lstsq_per_view():
    """The floor's fits of all views at once equal np.linalg.lstsq view by view, on a frame with
    a third of its pixels clipped, and on a view left with too few pixels for a quadratic."""
    from gaussian_atoms_method.physics.detector_floor import frame_mask, masked_least_squares, quadratic_basis

    rng = np.random.default_rng(0)
    mask = frame_mask((97, 81), 0.08)
    basis = quadratic_basis((97, 81))[:, mask].T
    values = rng.normal(size=(5, len(basis))) + (basis @ rng.normal(size=(6, 5))).T
    keep = rng.random(values.shape) > 0.33
    keep[4] = False
    keep[4, :3] = True  # three pixels: an underdetermined fit
    fitted = masked_least_squares(basis, values, keep)
    for v in range(5):
        expected = np.linalg.lstsq(basis[keep[v]], values[v, keep[v]], rcond=None)[0]
        np.testing.assert_allclose(fitted[v], expected, rtol=1e-10 if v < 4 else 1e-6, atol=1e-10 if v < 4 else 1e-6)


def test_medians_on_a_device_are_numpys():
    """The noise reading's medians in torch (a GPU's path, run here on the CPU) equal numpy's,
    for odd and even counts, and the binned robust variances with them, to float64 rounding."""
    import torch

    from gaussian_atoms_method.physics.noise import binned_variance, median_on_device

    rng = np.random.default_rng(3)
    for n in (1, 2, 7, 1000):
        x = rng.standard_normal(n)
        assert float(median_on_device(torch.as_tensor(x))) == np.median(x)
    predicted = rng.uniform(0.0, 50.0, 20001)
    residuals = rng.standard_normal(20001) * np.sqrt(4.0 + 0.5 * predicted)
    expected = binned_variance(residuals, predicted)  # numpy's path: no GPU here
    got = binned_variance(residuals, predicted, device="cpu")  # the medians in torch
    for a, b in zip(got, expected):
        np.testing.assert_allclose(a, b, rtol=1e-12)


def test_equal_count_bins_are_the_stable_sorts():
    """The noise reading's bins, found without a sort, are ``np.array_split`` of the stable
    sorted order exactly: continuous values, counts with many ties (ties at the edges split in
    index order), and more bins than values."""
    from gaussian_atoms_method.physics.noise import equal_count_bins

    rng = np.random.default_rng(1)
    for trial in range(120):
        n, bins = int(rng.integers(1, 400)), int(rng.integers(1, 30))
        values = [
            rng.standard_normal(n),
            rng.integers(0, 1 + trial % 5, n).astype(np.float64),
            np.round(rng.standard_normal(n), 1),
        ][trial % 3]
        chunks = np.array_split(np.argsort(values, kind="stable"), bins)
        expected = np.empty(n, dtype=np.int64)
        for k, chunk in enumerate(chunks):
            expected[chunk] = k
        label, sizes = equal_count_bins(values, bins)
        np.testing.assert_array_equal(label, expected)
        np.testing.assert_array_equal(sizes, [len(c) for c in chunks])


def test_the_noise_read_beside_the_start_is_the_one_read_in_line():
    """engine.noise_reading.NoiseReadingBeside reads in a thread what noise_reading reads in line
    (float64 data, the same bits), reads again in line for another noise (a start begun ahead
    and not taken), and raises the thread's error in the caller."""
    from dataclasses import replace

    import torch

    from gaussian_atoms_method.engine.noise_reading import NoiseReadingBeside, noise_reading
    from gaussian_atoms_method.physics.noise import measure_noise

    rng = np.random.default_rng(5)
    data = 1.5 + rng.normal(0.0, 0.2, (6, 48, 48))
    data[:, 18:30, 18:30] += 4.0
    projections = torch.from_numpy(data)
    noise = measure_noise(projections)
    in_line = noise_reading(projections, "auto", "auto", noise)
    beside = NoiseReadingBeside(projections, "auto", "auto", noise).result(noise)
    assert beside[0] == in_line[0] and beside[1:3] == in_line[1:3] and beside[4] == in_line[4]
    assert (beside[3] is None) == (in_line[3] is None)
    assert beside[3] is None or np.array_equal(beside[3], in_line[3])
    other = replace(noise, read_var=2.0 * noise.read_var)
    assert NoiseReadingBeside(projections, "auto", "auto", noise).result(other)[0] == other
    with pytest.raises(ValueError):  # one image row: no frame to read
        NoiseReadingBeside(projections[0, 0], "auto", "auto", noise).result(noise)


def test_host_mad_leaves_its_input_and_equals_the_plain_formula():
    """The host's MAD (medians partitioned in place, in its own copy) equals the formula written
    plainly in float64, with and without non-finite values, and leaves the caller's array as it
    was."""
    import torch

    from gaussian_atoms_method.physics.noise import MAD_TO_STD, mad_std

    rng = np.random.default_rng(5)
    for n in (1, 2, 7, 10001):
        x = rng.standard_normal(n) * 3.0 + 1.0
        if n > 2:
            x[[0, n // 2]] = [np.nan, np.inf]
        kept = x.copy()
        v = x[np.isfinite(x)]
        assert mad_std(x) == float(MAD_TO_STD * np.median(np.abs(v - np.median(v))))
        np.testing.assert_array_equal(x, kept)
        as_float32 = torch.as_tensor(x, dtype=torch.float32)
        v32 = as_float32.numpy().astype(np.float64)
        v32 = v32[np.isfinite(v32)]
        assert mad_std(as_float32) == float(MAD_TO_STD * np.median(np.abs(v32 - np.median(v32))))


@pytest.fixture(scope="module")
def shifted_stacks():
    """A 135-atom Au sphere (Gaussian atoms, 0.61 Å wide, 0.25 Å pixels) with white noise of a
    known variance, and the same views shifted by random sub-pixel amounts with splines of
    orders 1, 3 and 5, as a crop or an alignment interpolates them: the noise correlated, its
    power at the atoms' scale still the white noise's (an interpolation keeps the mean)."""
    from scipy import ndimage

    from gaussian_atoms_method.harness.simulate import simulate_tilt_series, spherical_particle

    angles = np.arange(-70.0, 71.0, 5.0)
    sim = simulate_tilt_series(spherical_particle("Au", radius_A=8.0), angles, potential="gaussian", noise_std=0.0)
    clean = sim.projections.astype(np.float64)
    rng = np.random.default_rng(1)
    std = 0.05 * clean.max()
    white = clean + rng.normal(0.0, std, clean.shape)
    shifts = rng.uniform(-0.5, 0.5, size=(len(clean), 2))
    stacks = {order: np.stack([ndimage.shift(v, s, order=order, mode="nearest") for v, s in zip(white, shifts)])
              for order in (1, 3, 5)}  # fmt: skip
    return white, stacks, std**2


@pytest.mark.parametrize("order", [1, 3, 5])
def test_the_noise_of_an_interpolated_correlated_stack_is_read_within_20_percent(shifted_stacks, order):
    """Read from neighbouring pixels the shifted stacks hold 0.22-0.66 of their noise; read from
    the spectrum beyond the atoms, carried to the atoms' frequencies, within 20% of it (here
    within 5%), and the reading says it is correlated."""
    from gaussian_atoms_method.physics.noise import measure_noise, noise_from_projections

    _, stacks, variance = shifted_stacks
    views = stacks[order]
    level = np.array([views.mean()])
    assert noise_from_projections(views).variance(level)[0] < 0.8 * variance
    noise = measure_noise(views)
    assert noise.correlation > 1.2
    assert noise.variance(level)[0] == pytest.approx(variance, rel=0.2)


def test_white_noise_reads_uncorrelated_and_its_reading_is_left_as_it_was(shifted_stacks):
    """The same views before the shift: the band beyond the atoms is flat, so the neighbouring
    pixels' reading stands, to the bit (every white-noise run reads as before)."""
    from gaussian_atoms_method.physics.noise import measure_noise, noise_from_projections
    from gaussian_atoms_method.physics.noise_spectrum import noise_spectrum

    white, _, variance = shifted_stacks
    spectrum = noise_spectrum(white)
    assert not spectrum.correlated and spectrum.fall == pytest.approx(1.0, abs=0.05)
    assert spectrum.level == pytest.approx(variance, rel=0.05)
    assert measure_noise(white) == noise_from_projections(white)


def test_views_blurred_at_every_frequency_the_atoms_leave_read_no_band(shifted_stacks):
    """A Gaussian blur of 0.7 px (a denoiser's, or the Ta film's views, whose spectrum falls
    steeply up to Nyquist) leaves no band of noise alone: nothing is read from the spectrum (the
    run then judges by its residual), rather than a level that would be 80 times too low."""
    from scipy import ndimage

    from gaussian_atoms_method.physics.noise import measure_noise, noise_from_projections
    from gaussian_atoms_method.physics.noise_spectrum import noise_spectrum

    blurred = ndimage.gaussian_filter(shifted_stacks[0], (0, 0.7, 0.7))
    assert noise_spectrum(blurred) is None
    noise = measure_noise(blurred)
    assert not noise.correlation_read and noise.correlation == 1.0
    assert dataclasses.replace(noise, correlation_read=True) == noise_from_projections(blurred)


def test_the_spectrum_in_torch_is_numpys(shifted_stacks):
    import torch

    from gaussian_atoms_method.physics.noise_spectrum import mean_power

    views = shifted_stacks[1][3][:4]
    np.testing.assert_allclose(mean_power(views, torch.device("cpu")), mean_power(views), rtol=1e-10, atol=1e-9)
