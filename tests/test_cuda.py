"""The CUDA paths agree with the CPU reference (skipped without a CUDA device or gsplat's CUDA)."""

import numpy as np
import pytest
import torch

from gaussian_atoms_method.physics.geometry import detector_axes_from_tilts
from gaussian_atoms_method.physics.projector import project_gaussians, project_gaussians_gsplat, project_gaussians_tiled

cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")


def _scene(device, dtype, n=3000, pixels=128):
    g = torch.Generator().manual_seed(0)
    means = ((torch.rand(n, 3, generator=g) - 0.5) * 1.2).to(device, dtype)  # some beyond the edge
    sigmas = (0.005 + 0.02 * torch.rand(n, generator=g)).to(device, dtype)
    amps = (10 ** (2 * torch.rand(n, generator=g) - 1)).to(device, dtype)
    axes = torch.tensor(detector_axes_from_tilts(np.array([-65.0, 0.0, 20.0, 88.0]), "y"), dtype=dtype, device=device)
    coords = ((torch.arange(pixels) + 0.5 - pixels / 2) / pixels).to(device, dtype)
    return means, sigmas, amps, axes, coords


def _value_and_grads(project, scene):
    params = [t.clone().requires_grad_() for t in scene[:3]]
    img = project(*params, *scene[3:], scene[4])
    weights = torch.linspace(0.5, 1.5, img.numel(), device=img.device, dtype=img.dtype).reshape(img.shape)
    (img * weights).sum().backward()
    return img.detach().double().cpu(), [p.grad.double().cpu() for p in params]


@cuda
@pytest.mark.parametrize("name", ["dense", "tiled", "gsplat"])
def test_cuda_projectors_match_cpu_float64(name):
    """float32 on CUDA (TF32 off) against float64 on CPU: values within 1e-5 of the peak,
    gradients within 1e-3 of their largest (float32 resolution after sums of thousands)."""
    torch.backends.cuda.matmul.allow_tf32 = False
    project = {"dense": project_gaussians, "tiled": project_gaussians_tiled, "gsplat": project_gaussians_gsplat}[name]
    if name == "gsplat":
        pytest.importorskip("gsplat")
        from gsplat.cuda._backend import _C

        if _C is None:
            pytest.skip("gsplat's CUDA extension is not built")
    ref, ref_grads = _value_and_grads(project_gaussians, _scene("cpu", torch.float64))
    got, grads = _value_and_grads(project, _scene("cuda", torch.float32))
    assert float((got - ref).abs().max()) <= 1e-5 * float(ref.abs().max())
    for g, r in zip(grads, ref_grads):
        assert float((g - r).abs().max()) <= 1e-3 * float(r.abs().max())


def test_gsplat_projector_refuses_cpu():
    scene = _scene("cpu", torch.float32, n=3)
    with pytest.raises(ValueError, match="needs a CUDA device"):
        project_gaussians_gsplat(*scene[:3], *scene[3:], scene[4])


@cuda
def test_filtered_backprojection_on_cuda_matches_cpu():
    """The sparse-matrix FBP gives the same slices on the GPU (cuSPARSE, float64) as on the CPU."""
    from gaussian_atoms_method.physics.reconstruction import filtered_backprojection

    rng = np.random.default_rng(1)
    sino = rng.normal(size=(4, 41, 17))
    theta = np.linspace(-70, 68, 17)
    cpu = filtered_backprojection(sino, theta, "hann", 41)
    gpu = filtered_backprojection(sino, theta, "hann", 41, device="cuda", max_matrix_entries=300 * 34)
    np.testing.assert_allclose(gpu, cpu, rtol=0, atol=1e-10 * np.abs(cpu).max())
    # float32 (the start's): filtered and back-projected in float32, to its rounding
    single = filtered_backprojection(sino, theta, "hann", 41, device="cuda", dtype=torch.float32)
    np.testing.assert_allclose(single, cpu, rtol=0, atol=1e-5 * np.abs(cpu).max())


@cuda
def test_noise_readings_on_cuda_equal_the_hosts():
    """The pre-fit noise model, the fitted one and the excess over an atom read on the GPU (what
    a run there does) equal those read on the CPU in float64 (which test_noise holds to numpy's)."""
    from dataclasses import astuple

    from gaussian_atoms_method.physics.noise import atom_scale_excess, fit_noise_model, noise_from_projections

    rng = np.random.default_rng(2)
    rows, cols = np.arange(120)[:, None], np.arange(101)[None]
    mean = np.broadcast_to(3.0 + 40.0 * np.exp(-((rows - 60) ** 2 + (cols - 50) ** 2) / 300.0), (11, 120, 101)).copy()
    data = rng.poisson(mean).astype(np.float64)
    for a, b in zip(
        astuple(noise_from_projections(data, device="cpu")),
        astuple(noise_from_projections(torch.tensor(data, device="cuda"))),
    ):
        assert b == pytest.approx(a, rel=1e-9, abs=1e-12)
    r, m = torch.tensor(data - mean, device="cuda"), torch.tensor(mean, device="cuda")
    for a, b in zip(astuple(fit_noise_model(data - mean, mean, device="cpu")), astuple(fit_noise_model(r, m))):
        assert b == pytest.approx(a, rel=1e-9, abs=1e-12)
    assert atom_scale_excess(r, m, 1.5) == pytest.approx(
        atom_scale_excess(data - mean, mean, 1.5, device="cpu"), rel=1e-9
    )


@cuda
def test_backprojected_noise_variance_on_cuda_equals_the_hosts():
    """The start's per-pixel noise variance, filtered on the GPU, equals the host's scipy filter;
    so do its mean and its 99th percentile, the levels' scales."""
    from gaussian_atoms_method.atoms.candidates import backprojected_noise, percentile
    from gaussian_atoms_method.physics.noise import NoiseModel

    rng = np.random.default_rng(6)
    projections = rng.gamma(2.0, 10.0, (9, 70, 61))
    angles, noise = np.linspace(-60.0, 60.0, 9), NoiseModel(4.0, 0.7)
    sample_host, host = backprojected_noise(projections, angles, 0.4, "y", "cpu", noise=noise)
    sample_gpu, gpu = backprojected_noise(projections, angles, 0.4, "y", "cuda", noise=noise)
    np.testing.assert_allclose(gpu.cpu().numpy(), host, rtol=1e-12)
    assert float(gpu.mean()) == pytest.approx(float(host.mean()), rel=1e-12)
    assert percentile(gpu, 99.0) == pytest.approx(percentile(host, 99.0), rel=1e-12)


@cuda
def test_slice_planes_on_cuda_equal_the_hosts():
    """The slices picture's planes, multiplied out on the GPU in float64, equal numpy's."""
    from gaussian_atoms_method.atoms.atom_set import AtomSet
    from gaussian_atoms_method.atoms.slices import potential_on_plane

    rng = np.random.default_rng(8)
    atoms = AtomSet(rng.uniform(-9, 9, (500, 3)), sigmas=rng.uniform(0.3, 0.8, 500), amplitudes=rng.uniform(1, 3, 500))
    coords = np.linspace(-10, 10, 301)
    host = potential_on_plane(atoms, 2, 0.5, 0, 1, coords, coords)
    np.testing.assert_allclose(
        potential_on_plane(atoms, 2, 0.5, 0, 1, coords, coords, device="cuda"),
        host,
        rtol=1e-10,
        atol=1e-12 * host.max(),
    )


@cuda
def test_clusters_on_cuda_equal_the_hosts():
    """The training merge's clusters found on the GPU equal the host k-d tree's, numbering included."""
    from gaussian_atoms_method.atoms.merge import cluster_labels, cluster_labels_on_device

    rng = np.random.default_rng(4)
    pos = (rng.random((20000, 3)) * 40.0).astype(np.float32)
    mergeable = rng.random(20000) > 0.1
    labels, count = cluster_labels_on_device(
        torch.tensor(pos, device="cuda"), 0.6, torch.tensor(mergeable, device="cuda")
    )
    expected = cluster_labels(pos, 0.6, mergeable)
    assert count == expected[1] < 20000 and np.array_equal(labels, expected[0])


@cuda
def test_auto_views_per_step_on_a_gpu_stays_within_its_memory_share():
    """On a GPU auto picks 1 to 8 views, never more than half the free memory holds by the
    projector's measured bytes per view (:func:`gaussian_atoms_method.engine.step_views.auto_views_per_step`)."""
    from gaussian_atoms_method.engine import step_views as SV

    coords = torch.arange(128.0, device="cuda") - 63.5
    views = SV.auto_views_per_step(project_gaussians, 3000, 47, coords, coords)
    free = torch.cuda.mem_get_info()[0] + torch.cuda.memory_reserved() - torch.cuda.memory_allocated()
    assert 1 <= views <= SV.MAX_VIEWS_PER_STEP
    assert (
        views * SV.projector_bytes_per_view(project_gaussians, 3000, coords, coords) <= SV.MEMORY_SHARE * free
        or views == 1
    )


@cuda
def test_a_training_step_never_waits_for_the_gpu(tmp_path):
    """A training step (batched views, a floor solved in closed form) queues its work without
    waiting for the GPU: under ``torch.cuda.set_sync_debug_mode("error")`` any synchronising
    call raises.  Each wait lets the GPU run dry while the host prepares the next kernels."""
    from dataparsers.tilt_series_dataparser import TiltSeriesDataParserConfig
    from dataparsers.tilt_series_format import write_tilt_series
    from gaussian_atoms_method.atoms.atom_set import AtomSet
    from gaussian_atoms_method.nerfstudio_layer.model import GaussianAtomsModelConfig

    rng = np.random.default_rng(0)
    write_tilt_series(
        tmp_path,
        rng.uniform(0, 10, size=(5, 30, 36)).astype(np.float32),
        np.array([-50.0, -10.0, 0.0, 25.0, 60.0]),
        0.3,
        truth=AtomSet(np.zeros((1, 3)), species=["Au"]),
    )
    outputs = TiltSeriesDataParserConfig(data=tmp_path).setup().get_dataparser_outputs("train")
    model = (
        GaussianAtomsModelConfig(num_random=50, views_per_step=3, background="constant", coarse_steps=0)
        .setup(scene_box=outputs.scene_box, num_train_data=5, metadata=outputs.metadata)
        .to("cuda")
    )
    model.train()
    images = torch.as_tensor(outputs.metadata["projections"], device="cuda")
    cameras = [outputs.cameras[v : v + 1].to("cuda") for v in range(5)]  # as the datamanager serves them
    for v, camera in enumerate(cameras):
        camera.metadata = {"cam_idx": v}

    def step(v):
        loss = model.get_loss_dict(model.get_outputs(cameras[v]), {"image": images[v][..., None]})["main_loss"]
        loss.backward()

    for v in range(5):  # each camera is read from the GPU once, then served from the model's cache
        step(v)
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        for v in range(5):
            step(v)
    finally:
        torch.cuda.set_sync_debug_mode("default")
    model.finite_watch.flush()


@cuda
def test_clean_with_pairs_found_on_cuda_equals_the_hosts():
    """CLEAN with its pairs found on the GPU accepts the same peaks with the same amounts (to
    float64 rounding: the visit sums each peak's pairs in another order) as the host's."""
    from gaussian_atoms_method.atoms.point_response import clean_peaks

    rng = np.random.default_rng(3)
    grid = np.indices((21, 21, 31)) - np.array([10, 10, 15])[:, None, None, None]
    response = np.exp(-(grid[0] ** 2 + grid[1] ** 2) / 8 - grid[2] ** 2 / 60) - 0.1 * np.exp(
        -(grid**2).sum(axis=0) / 90
    )
    peaks = np.unique(rng.integers(0, 80, (6000, 3)), axis=0)
    peaks = peaks[rng.permutation(len(peaks))]
    values = np.sort(rng.uniform(0.5, 10.0, len(peaks)))[::-1]
    host, gpu = (
        clean_peaks(peaks, values, response, np.array([10, 10, 15]), 2.0),
        clean_peaks(peaks, values, response, np.array([10, 10, 15]), 2.0, "cuda"),
    )
    assert 0.2 * len(peaks) < len(host[0]) < len(peaks)
    assert host[0].tolist() == gpu[0].tolist()
    np.testing.assert_allclose(gpu[1], host[1], rtol=1e-12)


@cuda
def test_separated_maxima_on_cuda_equal_the_hosts():
    """The maxima and their strongest-first suppression on the GPU keep the voxels the host's
    search keeps, in the same order."""
    from scipy import ndimage

    from gaussian_atoms_method.atoms import maxima

    field = ndimage.gaussian_filter(np.random.default_rng(6).standard_normal((60, 50, 70)), 1.2)
    expected = maxima.separated_maxima_host(field, 0.25, 1.0, 0.01)
    assert len(expected) > 100
    np.testing.assert_array_equal(
        maxima.separated_maxima_device(torch.as_tensor(field, device="cuda"), 0.25, 1.0, 0.01), expected
    )


def _train(data, out, graphs: bool, steps: int, views: int):
    """A short run on the GPU through nerfstudio's trainer; returns the model."""
    from gaussian_atoms_method.nerfstudio_layer.launch import build_config, make_trainer

    config = build_config(
        [
            "--machine.device-type",
            "cuda",
            "--vis",
            "tensorboard",
            "--output-dir",
            str(out),
            "--timestamp",
            "run",
            "--max-num-iterations",
            str(steps),
            "--pipeline.model.cuda-graphs",
            str(graphs),
            "--pipeline.model.views-per-step",
            str(views),
            "--pipeline.model.coarse-steps",
            "20",
            "--pipeline.model.warmup-length",
            "30",
            "--pipeline.model.refine-every",
            "20",
            "--pipeline.model.merge-every",
            "20",
            "--pipeline.model.stop-when-converged",
            "False",
            "tilt-series",
            "--data",
            str(data),
        ]
    )
    trainer = make_trainer(config)
    trainer.train()
    return trainer.pipeline.model


@cuda
@pytest.mark.parametrize("views", [1, 3])
def test_steps_replayed_as_a_cuda_graph_train_as_eager_steps(tmp_path, views):
    """Captured and replayed (:mod:`.step_graph`), a run's steps do the arithmetic of the eager
    ones: through the coarse phase's end, refines and merges (each captured again), the same
    Gaussians, positions to float32 rounding carried over 70 Adam steps (1e-4 of the 0.5 Å
    pixel, in normalised units), the same floors and kernel."""
    from dataparsers.tilt_series_format import write_tilt_series
    from gaussian_atoms_method.harness.simulate import simulate_tilt_series, spherical_particle

    truth = spherical_particle("Au", radius_A=5.0)
    sim = simulate_tilt_series(
        truth, np.arange(-70.0, 71.0, 10.0), potential="gaussian", noise_std=20.0, floor_fraction=0.05, seed=0
    )
    data = write_tilt_series(tmp_path / "series", sim.projections, sim.angles_deg, sim.pixel_size_A, truth=truth)
    eager = _train(data, tmp_path / "eager", False, 70, views)
    graphed = _train(data, tmp_path / "graphed", True, 70, views)
    assert graphed.step_graph._off == "" and eager.step_graph._off == "--pipeline.model.cuda-graphs False"
    # Captured again at the coarse phase's end, the floors' sharing and each refine; the other steps replayed.
    assert graphed.step_graph.captures >= 3 and graphed.step_graph.replays >= 50 and eager.step_graph.replays == 0
    assert graphed.num_points == eager.num_points
    pixel = 1.0 / max(sim.projections.shape[1:])
    torch.testing.assert_close(graphed.means, eager.means, rtol=0, atol=1e-4 * pixel)
    for name in ("log_sigmas", "log_amplitudes"):
        torch.testing.assert_close(graphed.gauss_params[name], eager.gauss_params[name], rtol=0, atol=1e-4)
    for name, param in eager.view_params.items():
        torch.testing.assert_close(graphed.view_params[name], param, rtol=1e-4, atol=1e-6)


@cuda
def test_kernel_on_cuda_by_matrices_equals_the_hosts_fft():
    """On a GPU the point-spread function is applied by matrix products (no cuFFT): the host's
    FFT blur to float64 rounding (1e-9 of the peak, as tests/test_psf.py argues), with the
    weights' gradient."""
    from gaussian_atoms_method.physics.psf import KERNEL_WIDTHS_A, apply_kernel

    image = torch.rand(2, 48, 61, dtype=torch.float64, generator=torch.Generator().manual_seed(5))
    results = []
    for device in ("cpu", "cuda"):
        weights = torch.tensor([0.2, 0.1, 0.3], dtype=torch.float64, device=device, requires_grad=True)
        blurred = apply_kernel(image.to(device), 0.3, tuple(KERNEL_WIDTHS_A), weights)
        (grad,) = torch.autograd.grad((blurred * image.to(device)).sum(), weights)
        results.append((blurred.detach().cpu(), grad.cpu()))
    assert float((results[0][0] - results[1][0]).abs().max()) < 1e-9 * float(results[0][0].max())
    assert torch.allclose(results[0][1], results[1][1], rtol=1e-9, atol=0.0)


@cuda
def test_large_images_on_cuda_are_blurred_by_fft(monkeypatch):
    """Beyond MATRIX_BLUR_MAX_SIDE_PX a GPU blurs by FFT (the products' work grows as the side
    cubed): the same images as the host's to float64 rounding, without the matrices."""
    from gaussian_atoms_method.physics import psf

    side = psf.MATRIX_BLUR_MAX_SIDE_PX + 1
    image = torch.rand(1, side, 40, dtype=torch.float64, generator=torch.Generator().manual_seed(6))
    weights = torch.tensor([0.2, 0.1, 0.3], dtype=torch.float64)
    host = psf.apply_kernel(image, 0.3, tuple(psf.KERNEL_WIDTHS_A), weights)

    def refused(*args):
        raise AssertionError("a large image was blurred by matrices")

    monkeypatch.setattr(psf, "apply_kernel_by_matrices", refused)
    gpu = psf.apply_kernel(image.cuda(), 0.3, tuple(psf.KERNEL_WIDTHS_A), weights.cuda()).cpu()
    assert float((gpu - host).abs().max()) < 1e-12 * float(host.max())


def _engine_run(series, out, graphs: bool, steps: int, device: str = "cuda"):
    """The engine's own loop (``gaussian-atoms train``, ``ga.reconstruct``) on ``series``, as
    :func:`_train` sets nerfstudio's up."""
    from gaussian_atoms_method.engine.fit import AtomFit
    from gaussian_atoms_method.engine.options import FitOptions
    from gaussian_atoms_method.engine.run import view_set_of
    from gaussian_atoms_method.engine.training import FitLoop, LoopSettings, run_pass

    options = FitOptions(
        cuda_graphs=graphs,
        coarse_steps=20,
        warmup_length=30,
        refine_every=20,
        merge_every=20,
        stop_when_converged=False,
    )
    view_set, views = view_set_of(series)
    fit = AtomFit(options, view_set).to(device)
    loop = FitLoop(fit, views, view_set.projections, steps)
    run_pass(loop, out, LoopSettings(steps, steps, 0, checkpoints=False))
    return fit


@cuda
def test_the_engines_replayed_steps_train_as_its_eager_steps(tmp_path):
    """The engine's own loop (not nerfstudio's trainer, tested above) replays its captured steps
    to the arithmetic of its eager ones: after 70 steps through the coarse phase's end, refines
    and merges, the same Gaussians to float32 rounding carried over 70 Adam steps (as above)."""
    from gaussian_atoms_method.api import _as_series
    from gaussian_atoms_method.harness.simulate import simulate_tilt_series, spherical_particle

    truth = spherical_particle("Au", radius_A=5.0)
    sim = simulate_tilt_series(
        truth, np.arange(-70.0, 71.0, 10.0), potential="gaussian", noise_std=20.0, floor_fraction=0.05, seed=0
    )
    series = _as_series(sim.projections, sim.angles_deg, sim.pixel_size_A, "y", ())
    eager = _engine_run(series, tmp_path / "eager", False, 70)
    graphed = _engine_run(series, tmp_path / "graphed", True, 70)
    assert graphed.step_graph._off == "" and graphed.step_graph.captures >= 3 and graphed.step_graph.replays >= 50
    assert eager.step_graph.replays == 0 and graphed.num_points == eager.num_points
    pixel = 1.0 / max(sim.projections.shape[1:])
    torch.testing.assert_close(graphed.means, eager.means, rtol=0, atol=1e-4 * pixel)
    for name in ("log_sigmas", "log_amplitudes"):
        torch.testing.assert_close(graphed.gauss_params[name], eager.gauss_params[name], rtol=0, atol=1e-4)


@cuda
def test_the_evidence_on_cuda_equals_the_hosts():
    """Each atom's evidence on a GPU (the moved blocks read in each batch, the sets solved there)
    is the host's (the moved blocks read once, :class:`~gaussian_atoms_method.atoms.depth_profile.MovedBlocks`)
    to float64's rounding: 150 atoms of an fcc lattice, whose depth profile moves columns."""
    from test_evidence import _fcc_evidence_inputs

    from gaussian_atoms_method.atoms.evidence import atom_evidence

    read, moved = _fcc_evidence_inputs()
    host = atom_evidence(*read, moved_pulls=moved, device="cpu")
    gpu = atom_evidence(*read, moved_pulls=moved, device="cuda")
    scale = np.nanmax(np.abs(host.depth_profile))
    np.testing.assert_allclose(gpu.depth_profile, host.depth_profile, rtol=1e-9, atol=1e-9 * scale)
    np.testing.assert_allclose(gpu.position_std_A, host.position_std_A, rtol=1e-9)
    np.testing.assert_allclose(gpu.significance, host.significance, rtol=1e-9)
    np.testing.assert_array_equal(gpu.depth_open, host.depth_open)
