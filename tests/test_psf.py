"""The learned point-spread function: exact on a Gaussian, mass-conserving, recovered from data."""

import math

import numpy as np
import pytest
import torch

from gaussian_atoms_method.physics.psf import (
    KERNEL_WIDTHS_A,
    apply_kernel,
    apply_kernel_by_matrices,
    fast_fft_length,
    kernel_transfer,
    project_weights,
)


def test_kernel_of_one_gaussian_blurs_a_gaussian_exactly_and_keeps_mass():
    """All weight on one width s: a 2D Gaussian of width a becomes one of width sqrt(a^2 + s^2)
    (float64, to 1e-9 of the peak); any weights keep the image's sum (K^(0) = 1) while the
    blurred image stays on the detector (64 Å here, against the 4 Å width's reach of 16 Å)."""
    n, spacing, a, s = 256, 0.25, 0.6, 1.0
    x = (torch.arange(n, dtype=torch.float64) - n / 2) * spacing
    r2 = x[:, None] ** 2 + x[None, :] ** 2
    image = torch.exp(-r2 / (2 * a**2)) / (2 * math.pi * a**2)
    blurred = apply_kernel(
        image[None], spacing, torch.tensor([s], dtype=torch.float64), torch.tensor([1.0], dtype=torch.float64)
    )[0]
    expected = torch.exp(-r2 / (2 * (a**2 + s**2))) / (2 * math.pi * (a**2 + s**2))
    assert float((blurred - expected).abs().max()) < 1e-9 * float(expected.max())
    mixed = apply_kernel(
        image[None],
        spacing,
        torch.tensor(KERNEL_WIDTHS_A, dtype=torch.float64),
        torch.tensor([0.3, -0.1, 0.2], dtype=torch.float64),
    )
    weights = torch.tensor([0.5, -3.0, 2.0], dtype=torch.float64)
    project_weights(weights)  # after each step: a non-negative kernel
    assert bool((weights >= 0).all()) and float(weights.sum()) == pytest.approx(1.0) and float(weights[1]) == 0.0
    # zero weights: identity
    assert torch.equal(apply_kernel(image[None], spacing, torch.tensor(KERNEL_WIDTHS_A), torch.zeros(3))[0], image)
    assert float(mixed.sum()) == pytest.approx(float(image.sum()), rel=1e-6)
    assert float(kernel_transfer(torch.zeros(1), torch.tensor([1.0]), torch.tensor([0.7]))) == 1.0


def test_kernel_from_host_widths_equals_the_tensor_form_with_its_gradient():
    """A training step gives the widths as host floats (the transfer's Gaussian factors kept per
    image grid): the same blurred images and weight gradient as the tensor form, in float64 to
    rounding (1e-12 of the image's peak), on two grids in turn (the coarse and full phases)."""
    spacing = 0.25
    for n in (64, 32, 64):
        image = torch.rand(2, n, n + 3, dtype=torch.float64, generator=torch.Generator().manual_seed(n))
        results = []
        for widths in (torch.tensor(KERNEL_WIDTHS_A, dtype=torch.float64), tuple(KERNEL_WIDTHS_A)):
            weights = torch.tensor([0.3, 0.1, 0.2], dtype=torch.float64, requires_grad=True)
            blurred = apply_kernel(image, spacing, widths, weights)
            (grad,) = torch.autograd.grad((blurred * image).sum(), weights)
            results.append((blurred.detach(), grad))
        assert float((results[0][0] - results[1][0]).abs().max()) < 1e-12 * float(image.max())
        assert torch.allclose(results[0][1], results[1][1], rtol=1e-12, atol=0.0)


def test_kernel_by_matrices_equals_the_ffts_with_its_gradients():
    """A GPU applies the kernel by separable matrix products (no cuFFT): the same blurred images
    and gradients (to the weights and the images) as the zero-padded FFT, in float64 to 1e-9 of
    the image's peak, the FFT's aliasing at a two-pixel width (exp(-2 pi^2) ~ 3e-9 of it) and its
    wrap-around beyond three widths of padding (exp(-18)) being below that; on a non-square image
    with a batch dimension, at the package's widths and pixel pitches of 0.25 and 0.5 Å."""
    for spacing in (0.25, 0.5):
        image = torch.rand(3, 40, 57, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
        results = []
        for apply in (apply_kernel, apply_kernel_by_matrices):
            pixels = image.clone().requires_grad_(True)
            weights = torch.tensor([0.3, 0.1, 0.2], dtype=torch.float64, requires_grad=True)
            blurred = apply(pixels, spacing, tuple(KERNEL_WIDTHS_A), weights)
            grads = torch.autograd.grad((blurred * image.flip(-1)).sum(), (weights, pixels))
            results.append((blurred.detach(), *grads))
        for fft, matrices in zip(*results):
            assert float((fft - matrices).abs().max()) < 1e-9 * float(fft.abs().max())


def test_fast_fft_length_is_the_smallest_product_of_twos_and_threes_not_below_n():
    """Brute force over 1..3000: every length a product of 2s and 3s, none smaller that is."""
    smooth = sorted({2**a * 3**b for a in range(13) for b in range(9)})
    for n in range(1, 3001):
        assert fast_fft_length(n) == next(m for m in smooth if m >= n)


def _blurred_series_and_model(tmp_path, true_weights: torch.Tensor, **options):
    """An Au sphere's (4 Å radius) 7 noise-free views (-60..60 deg) through the kernel ``true_weights``,
    and a model of as many Gaussians on them (no background, least squares)."""
    from dataparsers.tilt_series_dataparser import TiltSeriesDataParserConfig
    from dataparsers.tilt_series_format import write_tilt_series
    from gaussian_atoms_method.harness.simulate import simulate_gaussian_tilt_series, spherical_particle
    from gaussian_atoms_method.nerfstudio_layer.model import GaussianAtomsModelConfig

    atoms = spherical_particle("Au", radius_A=4.0)
    angles = np.linspace(-60, 60, 7)
    sim = simulate_gaussian_tilt_series(atoms, angles, noise_std=0.0, margin_A=10.0)
    proj = apply_kernel(
        torch.as_tensor(sim.projections, dtype=torch.float64),
        sim.pixel_size_A,
        torch.tensor(KERNEL_WIDTHS_A, dtype=torch.float64),
        true_weights,
    ).numpy()
    write_tilt_series(tmp_path, proj.astype(np.float32), angles, sim.pixel_size_A, truth=sim.truth)
    outputs = TiltSeriesDataParserConfig(data=tmp_path).setup().get_dataparser_outputs("train")
    model = GaussianAtomsModelConfig(
        num_random=len(atoms), init="random", coarse_steps=0, background="none", loss="l2", **options
    ).setup(scene_box=outputs.scene_box, num_train_data=len(outputs.image_filenames), metadata=outputs.metadata)
    return atoms, sim, angles, outputs, model


def test_kernel_is_recovered_from_a_simulated_series(tmp_path, fit_view_parameter):
    """Projections blurred by a kernel with 30% of the intensity in a 2 Å tail (the ladder's
    middle width): with the atoms known, the weights learned with the amplitudes (Adam, 800
    steps, noise-free) give back the kernel: its transfer function (the microscope's MTF) to 0.03
    at every frequency up to the detector's Nyquist, and the 2 Å tail's weight to 0.05 (the
    ladder's neighbours, 1 and 4 Å, take up a few per cent of it: they overlap over a small image)."""
    true_weights = torch.tensor([0.0, 0.3, 0.0], dtype=torch.float64)
    atoms, sim, angles, outputs, model = _blurred_series_and_model(tmp_path, true_weights)
    psf = model.view_params["psf"]
    learned = fit_view_parameter(model, outputs, atoms, sim, "psf", 1e-2, 800, lambda: project_weights(psf.data))
    learned = learned.double()
    widths = torch.tensor(KERNEL_WIDTHS_A, dtype=torch.float64)
    freq2 = torch.linspace(0.0, (0.5 / sim.pixel_size_A) ** 2, 200, dtype=torch.float64)
    assert (
        float((kernel_transfer(freq2, widths, learned) - kernel_transfer(freq2, widths, true_weights)).abs().max())
        < 0.03
    )
    assert abs(float(learned[1]) - 0.3) < 0.05


@pytest.mark.parametrize("kind", ["l2", "huber", "poisson"])
def test_kernel_weights_are_read_from_views_under_each_data_term(kind):
    """``fit_kernel_weights``: views blurred by a kernel with 5%, 20% and 10% of the intensity at
    1, 2 and 4 Å, on a floor, with noise at 1% of an atom's peak: the weights come back to 0.01
    under the least-squares, Huber and Poisson terms (the noise's own scatter of the weights, over
    23 views of 66 atoms, is a few thousandths), and a kernel-free series reads no kernel."""
    from gaussian_atoms_method.physics.data_terms import data_term
    from gaussian_atoms_method.physics.psf import fit_kernel_weights

    gen = torch.Generator().manual_seed(0)
    spacing, widths = 0.3, torch.tensor(KERNEL_WIDTHS_A, dtype=torch.float64)
    sites = torch.zeros(23, 151, 77, dtype=torch.float64)
    sites[:, 20:130:9, 10:70:7] = 1.0
    atoms = apply_kernel(
        sites, spacing, torch.tensor([0.5], dtype=torch.float64), torch.tensor([1.0], dtype=torch.float64)
    )
    peak, floor, true = float(atoms.max()), 0.3, torch.tensor([0.05, 0.2, 0.1], dtype=torch.float64)
    noise = 0.01 * peak
    gain = 1.0 if kind == "l2" else noise**2 / (floor + 0.5 * peak)  # Poisson-like: the noise at mid signal
    blurred = apply_kernel(atoms, spacing, widths, true) + floor

    def loss(p, m):
        return data_term(p, m, kind, gain, noise**2 if kind == "l2" else 0.0)

    measured = blurred + noise * torch.randn(blurred.shape, generator=gen, dtype=torch.float64)
    read = fit_kernel_weights(atoms, torch.tensor(floor, dtype=torch.float64), measured, spacing, widths, loss)
    assert float((read - true).abs().max()) < 0.01, read
    plain = atoms + floor + noise * torch.randn(blurred.shape, generator=gen, dtype=torch.float64)
    assert (
        float(fit_kernel_weights(atoms, torch.tensor(floor, dtype=torch.float64), plain, spacing, widths, loss).max())
        < 0.01
    )


def test_held_out_views_teach_the_kernel_not_the_atoms(tmp_path):
    """``psf held-out``: a step on an odd view leaves the atoms without a gradient (none, not a
    zero one: Adam and the densify statistics would count that), a step on an even view gives
    them one; with the atoms at the truth, the kernel read on the odd views (30% of the intensity
    in a 2 Å tail, noise-free) comes back to 0.02, and after ``stop_split_at`` every view teaches
    the atoms with the kernel held."""
    from gaussian_atoms_method.harness.simulate import gaussian_potential_parameters

    true_weights = torch.tensor([0.0, 0.3, 0.0], dtype=torch.float64)
    atoms, sim, angles, outputs, model = _blurred_series_and_model(tmp_path, true_weights, psf="held-out")
    norm = model.normalisation
    with torch.no_grad():
        model.gauss_params["means"].copy_(torch.as_tensor(norm.positions_from_A(atoms.positions), dtype=torch.float32))
        model.gauss_params["log_sigmas"].fill_(math.log(sim.truth.sigmas[0] * norm.length_scale))
        # the simulation's atoms, blurred to the truth's widths
        sigmas, peaks = gaussian_potential_parameters(atoms.species, 0.35)
        peaks = peaks * (sigmas / sim.truth.sigmas) ** 3
        model.gauss_params["log_amplitudes"].copy_(
            torch.log(torch.as_tensor(peaks * norm.data_scale / norm.length_scale, dtype=torch.float32))[:, None]
        )
    model.train()
    model.step = model.density.warmup_length
    targets = [outputs.metadata["projections"][v][..., None] for v in range(len(angles))]
    for view, teaches in ((1, False), (2, True)):
        for p in model.gauss_params.values():
            p.grad = None
        model.get_loss_dict(model.get_outputs(outputs.cameras[view : view + 1]), {"image": targets[view]})[
            "main_loss"
        ].backward()
        assert (model.means.grad is not None) == teaches
    model.kernel_reading.read(model, model.step)
    read = model.view_params["psf"].detach().double()
    assert float((read - true_weights).abs().max()) < 0.02, read
    model.step = model.density.stop_split_at
    model.kernel_reading.read(model, model.step)
    assert model.kernel_reading.settled and not model.kernel_reading.holds_out(1, model.step)
    assert torch.equal(model.view_params["psf"].detach().double(), read)


def test_held_out_reading_then_the_run_with_the_kernel_held(tmp_path):
    """``gaussian-atoms train --pipeline.model.psf held-out``: the reading pass stops where the
    kernel is held (``stop_split_at``) without reporting its atoms, the atoms start again with
    the kernel held, and the run's results come from that second pass (``psf.json`` says
    ``fixed`` at the reading; the fit of a noise-free series through 30% of the intensity in a
    2 Å tail holds a kernel that is not the identity)."""
    import json
    import re
    import subprocess
    import sys
    from pathlib import Path

    from dataparsers.tilt_series_format import write_tilt_series
    from gaussian_atoms_method.harness.simulate import simulate_gaussian_tilt_series, spherical_particle

    atoms = spherical_particle("Au", radius_A=4.0)
    angles = np.linspace(-60, 60, 13)
    sim = simulate_gaussian_tilt_series(atoms, angles, noise_std=0.0, margin_A=10.0)
    proj = apply_kernel(
        torch.as_tensor(sim.projections, dtype=torch.float64),
        sim.pixel_size_A,
        torch.tensor(KERNEL_WIDTHS_A, dtype=torch.float64),
        torch.tensor([0.0, 0.3, 0.0], dtype=torch.float64),
    )
    write_tilt_series(tmp_path / "series", proj.numpy().astype(np.float32), angles, sim.pixel_size_A, truth=sim.truth)
    cmd = [
        str(Path(sys.executable).parent / "gaussian-atoms"),
        "train",
        "--machine.device-type",
        "cpu",
        "--vis",
        "tensorboard",
        "--output-dir",
        str(tmp_path / "out"),
        "--timestamp",
        "run",
        "--max-num-iterations",
        "400",
        "--pipeline.model.psf",
        "held-out",
        "--pipeline.model.stop-split-at",
        "300",
        "tilt-series",
        "--data",
        str(tmp_path / "series"),
    ]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
    log = run.stdout + run.stderr
    assert log.count("the atoms start again on every view") == 1 and log.count("wrote ") == 1
    psf = json.loads(next((tmp_path / "out").rglob("psf.json")).read_text())
    read = [
        float(w)
        for w in re.search(r"read on the held-out views is held at ([0-9.]+), ([0-9.]+), ([0-9.]+)", log).groups()
    ]
    assert psf["psf"] == "fixed" and np.allclose(psf["intensity_fractions"], read, atol=1e-3), (psf, read)
    assert next((tmp_path / "out").rglob("atoms.xyz")).is_file()
