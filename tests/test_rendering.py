"""The per-view rendering pieces (engine/rendering.py), each on a constructed case."""

import math

import numpy as np
import pytest
import torch
from nerfstudio.cameras.cameras import Cameras, CameraType
from scipy.spatial.transform import Rotation

from gaussian_atoms_method.engine import rendering as R
from gaussian_atoms_method.engine import step_views as SV
from gaussian_atoms_method.engine.errors import OptionError
from gaussian_atoms_method.nerfstudio_layer.options import GaussianAtomsOptions


def _camera(c2w, h=6, w=8, f=10.0, kind=CameraType.ORTHOPHOTO):
    return Cameras(camera_to_worlds=c2w[None], fx=f, fy=f, cx=w / 2, cy=h / 2, width=w, height=h, camera_type=kind)


def test_binning_averages_two_by_two_blocks():
    image = torch.arange(6 * 8, dtype=torch.float64).reshape(6, 8, 1)
    binned = R.binned_like(image, torch.zeros(3, 4, 1))
    expected = image[..., 0].numpy().reshape(3, 2, 4, 2).mean(axis=(1, 3))
    np.testing.assert_array_equal(binned[..., 0].numpy(), expected)
    assert R.binned_like(image, image) is image  # same size: unchanged
    # an odd-sized view with channels, float32 and float64: a reshaped mean's values to the bit
    for dtype in (torch.float32, torch.float64):
        view = torch.rand(271, 273, 3, generator=torch.Generator().manual_seed(1), dtype=dtype) * 256
        mean = view[:270, :272].reshape(135, 2, 136, 2, 3).mean(dim=(1, 3))
        assert torch.equal(R.binned_like(view, torch.zeros(135, 136, 3)), mean)


def test_pixel_coordinates_are_centred_and_bin_like_the_data():
    c2w = torch.eye(4, dtype=torch.float64)[:3]
    rows, cols = R.pixel_coordinates(_camera(c2w), c2w, coarse=False, device="cpu", dtype=torch.float64)
    np.testing.assert_allclose(rows.numpy(), (np.arange(6) + 0.5 - 3) / 10)
    np.testing.assert_allclose(cols.numpy(), (np.arange(8) + 0.5 - 4) / 10)
    rows_c, cols_c = R.pixel_coordinates(_camera(c2w), c2w, coarse=True, device="cpu", dtype=torch.float64)
    np.testing.assert_allclose(rows_c.numpy(), rows.numpy().reshape(3, 2).mean(axis=1))
    np.testing.assert_allclose(cols_c.numpy(), cols.numpy().reshape(4, 2).mean(axis=1))


def test_perspective_camera_takes_its_magnification_at_the_tilt_centre():
    c2w = torch.eye(4, dtype=torch.float64)[:3].clone()
    c2w[:, 3] = c2w[:, 2] * 2.5  # 2.5 from the centre along the view axis
    rows, _ = R.pixel_coordinates(_camera(c2w, kind=CameraType.PERSPECTIVE), c2w, False, "cpu", torch.float64)
    np.testing.assert_allclose(rows.numpy(), 2.5 * (np.arange(6) + 0.5 - 3) / 10)


def test_rotation_about_the_tilt_axis_matches_a_rotation_matrix():
    axis = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    vectors = [torch.tensor(v, dtype=torch.float64) for v in ([1.0, 0.2, -0.3], [0.0, 0.0, 1.0])]
    angle = math.radians(7.0)
    rotated = R.rotate_about(vectors, axis, torch.tensor(angle, dtype=torch.float64))
    matrix = Rotation.from_rotvec(angle * axis.numpy()).as_matrix()
    for v, r in zip(vectors, rotated):
        np.testing.assert_allclose(r.numpy(), matrix @ v.numpy(), atol=1e-15)


def test_background_constant_and_plane():
    image = torch.zeros(3, 4, dtype=torch.float64)
    rows, cols = torch.linspace(-1, 1, 3, dtype=torch.float64), torch.linspace(-1, 1, 4, dtype=torch.float64)
    assert float(R.add_background(image, torch.tensor([2.0], dtype=torch.float64), rows, cols).max()) == 2.0
    plane = R.add_background(image, torch.tensor([2.0, 0.5, -1.0], dtype=torch.float64), rows, cols)
    np.testing.assert_allclose(plane.numpy(), 2.0 + 0.5 * rows.numpy()[:, None] - cols.numpy()[None, :])
    r, c = rows.numpy()[:, None], cols.numpy()[None, :]
    quadratic = R.add_background(image, torch.tensor([2.0, 0.5, -1.0, 0.3, -0.2, 0.7], dtype=torch.float64), rows, cols)
    np.testing.assert_allclose(
        quadratic.numpy(), 2.0 + 0.5 * r - c + 0.3 * r**2 - 0.2 * r * c + 0.7 * c**2, rtol=1e-15, atol=1e-15
    )


def test_floor_images_are_every_views_terms_summed_and_view_floors_add_the_binned_surfaces():
    """floor_images, a step's views in two matrix products, equals each view's terms
    coefficient x row^a x col^b summed one by one (float64); view_floors adds each view's frame
    surface, binned 2 x 2 like the image in the coarse phase, and indexes one view or several."""
    from types import SimpleNamespace

    rows, cols = torch.linspace(-0.7, 0.4, 9, dtype=torch.float64), torch.linspace(-0.3, 0.9, 12, dtype=torch.float64)
    coefficients = torch.randn(4, 6, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    for k in (1, 3, 6):
        expected = torch.stack(
            [
                sum(c[i] * rows[:, None] ** a * cols[None, :] ** b for i, (a, b) in enumerate(R.FLOOR_TERMS[:k]))
                for c in coefficients[:, :k]
            ]
        )
        torch.testing.assert_close(
            R.floor_images(coefficients[:, :k], R.coordinate_powers(rows, cols)), expected, rtol=0, atol=1e-13
        )
    surfaces = torch.rand(4, 18, 24, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    model = SimpleNamespace(
        view_params={"background": coefficients}, background_surfaces=surfaces, view_geometry=R.ViewGeometry()
    )
    coarse = R.coordinate_powers(rows, cols)  # a 9 x 12 detector: the 18 x 24 surfaces binned
    floors = R.view_floors(model, [2, 0], coarse, torch.float64)
    for floor, v in zip(floors, (2, 0)):
        torch.testing.assert_close(
            floor,
            R.floor_images(coefficients[v : v + 1], coarse)[0] + surfaces[v].reshape(9, 2, 12, 2).mean(dim=(1, 3)),
            rtol=0,
            atol=1e-13,
        )
    torch.testing.assert_close(
        R.view_floors(model, [1], coarse, torch.float64)[0],
        R.view_floors(model, [1, 3], coarse, torch.float64)[0],
        rtol=0,
        atol=1e-13,
    )
    # binned once per size
    assert model.view_geometry.surfaces(surfaces, 9, 12) is model.view_geometry.surfaces(surfaces, 9, 12)


def test_binned_views_bins_each_view_as_binned_like_does():
    views = torch.rand(3, 271, 273, generator=torch.Generator().manual_seed(2)) * 256
    binned = R.binned_views(views, 135, 136)
    for view, b in zip(views, binned):
        assert torch.equal(b, R.binned_like(view[..., None], torch.zeros(135, 136, 1))[..., 0])
    assert R.binned_views(views, 271, 273) is views


def test_a_floor_varying_within_the_views_learns_a_quadratic_correction_from_its_frame_surface():
    """With the frame's surfaces (a smooth floor) the background has six terms per view, the
    constant at the floor and the correction at zero (the fit starts on the frame's surface);
    a flat floor keeps its one constant and the plane option its three."""
    from types import SimpleNamespace

    surfaces = np.zeros((5, 8, 8))
    cfg = SimpleNamespace(background="auto", psf="none", refine_alignment=False, refine_gain=False, refine_tilts=False)
    params, buffers = R.view_parameters(cfg, 5, 1.5, surfaces, None, 1.0)
    assert params["background"].shape == (5, 6) and buffers["background_surfaces"].shape == (5, 8, 8)
    assert (params["background"][:, 0] == 1.5).all() and (params["background"][:, 1:] == 0).all()
    assert R.view_parameters(cfg, 5, 1.5, None, None, 1.0)[0]["background"].shape == (5, 1)
    assert R.view_parameters(SimpleNamespace(**{**vars(cfg), "background": "plane"}), 5, None, None, None, 1.0)[0][
        "background"
    ].shape == (5, 3)


def test_a_camera_is_a_view_by_the_index_it_carries_not_by_its_pose():
    """A camera marked with a view (``metadata[VIEW_KEY]``) is that view; one without the mark is
    none, even at a view's very pose (the viewer's camera snapped to a view)."""
    poses = torch.stack([torch.eye(4)[:3] + 0.1 * i for i in range(4)])
    marked, unmarked = _camera(poses[2]), _camera(poses[2])
    marked.metadata = {R.VIEW_KEY: 2, "cam_idx": 0}  # nerfstudio's cam_idx is not read
    assert R.view_of(marked) == 2 and R.view_of(unmarked) is None


def test_view_geometry_reads_a_views_camera_once():
    """A view's camera is read once and then served from the cache; a camera that is no view
    (the viewer's) is read each time."""
    poses = torch.stack([torch.eye(4)[:3] + 0.1 * i for i in range(4)])
    geometry, camera = R.ViewGeometry(), _camera(poses[2])
    camera.metadata = {R.VIEW_KEY: 2}
    first = geometry.read(camera, poses[2], False, "cpu", torch.float64)
    rows, cols = R.pixel_coordinates(camera, poses[2], False, "cpu", torch.float64)
    assert (
        torch.equal(first[0], rows) and torch.equal(first[1], cols) and first[2] == pytest.approx(0.1) and first[3] == 2
    )
    assert geometry.read(camera, poses[2], False, "cpu", torch.float64) is first
    # the coarse phase: its own entry
    assert geometry.read(camera, poses[2], True, "cpu", torch.float64)[0].shape == (3,)
    viewer = _camera(poses[2])
    assert geometry.read(viewer, poses[2], False, "cpu", torch.float64)[3] is None
    assert geometry.read(viewer, poses[2], False, "cpu", torch.float64) is not geometry.read(
        viewer, poses[2], False, "cpu", torch.float64
    )
    # the floors' coordinate powers: kept for the coordinates read kept, made each time for others
    powers = geometry.powers(first[0], first[1])
    assert geometry.powers(first[0], first[1]) is powers and all(
        torch.equal(p, q) for p, q in zip(powers, R.coordinate_powers(rows, cols))
    )
    shifted = first[0] - 0.1
    assert geometry.powers(shifted, first[1]) is not geometry.powers(shifted, first[1])


def test_finite_watch_names_the_first_bad_step_and_its_cause():
    """On the CPU a non-finite parameter stops at its own step; a finite step passes."""
    watch = R.FiniteWatch()
    params = {"means": torch.zeros(4, 3), "log_sigmas": torch.zeros(4, 1)}
    measured = torch.zeros(2, 2)
    watch.check(torch.tensor(1.0), params, measured, 5)
    params["log_sigmas"][1, 0] = float("inf")
    with pytest.raises(FloatingPointError, match=r"step 6: .* cause: 1 Gaussian\(s\) with non-finite log_sigmas"):
        watch.check(torch.tensor(float("nan")), params, measured, 6)
    with pytest.raises(FloatingPointError, match="measured projection holds NaN"):
        watch.check(torch.tensor(float("nan")), {"means": torch.zeros(4, 3)}, torch.full((2, 2), float("nan")), 7)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_finite_watch_on_a_gpu_judges_a_step_later_under_its_own_number():
    """On a GPU a step's counts are judged at the next step (or the flush), still naming the step
    and counting the Gaussians as they were then."""
    watch = R.FiniteWatch()
    params = {"means": torch.zeros(4, 3, device="cuda")}
    measured = torch.zeros(2, 2, device="cuda")
    watch.check(torch.tensor(1.0, device="cuda"), params, measured, 5)
    params["means"][1, 0] = float("nan")
    watch.check(torch.tensor(float("nan"), device="cuda"), params, measured, 6)  # queued, not judged yet
    params["means"][:] = float("nan")  # the next optimiser step spreads it
    with pytest.raises(FloatingPointError, match=r"step 6: .* cause: 1 Gaussian\(s\) with non-finite means"):
        watch.flush()


def test_other_views_are_distinct_and_never_the_view_itself():
    generator = torch.Generator().manual_seed(0)
    for view in range(5):
        others = SV.other_views(view, 5, 4, generator)
        assert len(others) == 3 and len(set(others.tolist())) == 3 and view not in others.tolist()
    assert len(SV.other_views(0, 3, 8, generator)) == 2  # at most every other view


def test_view_batches_refuse_what_they_cannot_do_by_name():
    poses = torch.eye(4)[:3].expand(3, 3, 4).clone()
    assert SV.check_view_batches(1, None, poses).numel() == 0  # one view: nothing to check
    with pytest.raises(OptionError, match="needs a tilt series"):
        SV.check_view_batches(4, None, poses)
    off = poses.clone()
    off[:, 0, 3] = 1.0  # the camera sits off its beam axis
    with pytest.raises(OptionError, match="beam axis"):
        SV.check_view_batches(4, np.zeros((3, 2, 2)), off)
    assert SV.check_view_batches(4, np.ones((3, 2, 2)), poses).shape == (3, 2, 2)


def test_auto_views_per_step_counts_the_projectors_memory_and_keeps_one_view_off_a_gpu():
    """The dense projector keeps (N, H) and (N, W) float32 tensors per view: the measured bytes
    per view grow linearly in the Gaussians (the same from samples of 256 and 2,048), lie
    between one and eight such pairs, and on a CPU auto is one view per step."""
    from gaussian_atoms_method.physics.projector import project_gaussians

    rows, cols = torch.arange(60.0) - 29.5, torch.arange(40.0) - 19.5
    small, large = (SV.projector_bytes_per_view(project_gaussians, 10_000, rows, cols, sample=s) for s in (256, 2048))
    assert small == pytest.approx(large, rel=1e-3)
    pair = 10_000 * (60 + 40) * 4
    assert pair <= small <= 8 * pair
    assert SV.auto_views_per_step(project_gaussians, 10_000, 47, rows, cols) == 1


@pytest.mark.parametrize("free_bytes, n_views, expected", [(1e12, 47, 8), (7e9, 47, 3), (1e12, 5, 5), (1e6, 47, 1)])
def test_auto_views_per_step_on_a_gpu_is_the_most_its_memory_holds_whatever_the_timing(
    monkeypatch, free_bytes, n_views, expected
):
    """On a GPU auto takes as many views as half the free memory holds (1 GB a view here), up to
    eight and the series' own: a function of the sizes alone, so one input takes one number
    (chosen by the projector's timing, one particle took 2 views in one run and 4 in the next)."""
    from types import SimpleNamespace

    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda device=None: (free_bytes, 2 * free_bytes))
    monkeypatch.setattr(torch.cuda, "memory_reserved", lambda device=None: 0)
    monkeypatch.setattr(torch.cuda, "memory_allocated", lambda device=None: 0)
    monkeypatch.setattr(SV, "projector_bytes_per_view", lambda *args, **kwargs: 1e9)
    on_gpu = SimpleNamespace(device=torch.device("cuda"))
    assert SV.auto_views_per_step(None, 50_000, n_views, on_gpu, on_gpu) == expected


@pytest.mark.parametrize(
    "options, named",
    [
        ({"views_per_step": 0}, "views-per-step"),
        ({"views_per_step": 4, "refine_tilts": True}, "--pipeline.model.refine-tilts"),
        ({"num_random": 0}, "num-random"),
        ({"init_sigma_A": 9.0}, "init-sigma-A"),
        ({"merge_threshold_A": -1.0}, "merge-threshold-A"),
    ],
)
def test_option_conflicts_are_named_before_anything_is_built(options, named):
    with pytest.raises(OptionError, match=named):
        GaussianAtomsOptions(**options).check()


def test_index_on_a_device_keeps_values_and_order():
    """A host index (list, tuple of pairs or CPU tensor) arrives as the same long tensor; a
    tensor already off the host is moved, never pinned (the CUDA path, pinned and asynchronous,
    is run by test_cuda.py's step without waits)."""
    assert torch.equal(R.index_on([3, 0, 2], "cpu"), torch.tensor([3, 0, 2]))
    assert torch.equal(R.index_on(R.FLOOR_TERMS[:3], torch.device("cpu")), torch.tensor([[0, 0], [1, 0], [0, 1]]))
    got = R.index_on(torch.tensor([1, 1], dtype=torch.int32), "cpu")
    assert got.dtype == torch.long and got.tolist() == [1, 1]
    if torch.cuda.is_available():
        on_gpu = torch.tensor([4, 5], device="cuda")
        assert torch.equal(R.index_on(on_gpu, "cuda"), on_gpu) and R.index_on([4, 5], "cuda").tolist() == [4, 5]


def test_training_views_rendered_in_chunks_are_the_views_rendered_one_by_one(tmp_path, monkeypatch):
    """Every training view in one projector call per chunk (:func:`.rendering.render_views`) gives
    each camera's own rendering (floors and the kernel included) to float32 rounding, and the
    residual correlations of probe Gaussians that the final likelihood merge reads the same sums;
    chunks of one view and of all views alike."""
    from dataparsers.tilt_series_dataparser import TiltSeriesDataParserConfig
    from dataparsers.tilt_series_format import write_tilt_series
    from gaussian_atoms_method.engine import residuals
    from gaussian_atoms_method.harness.simulate import simulate_tilt_series, spherical_particle
    from gaussian_atoms_method.nerfstudio_layer.model import GaussianAtomsModelConfig

    truth = spherical_particle("Au", radius_A=4.0)
    sim = simulate_tilt_series(
        truth, np.arange(-60.0, 61.0, 20.0), potential="gaussian", noise_std=5.0, floor_fraction=0.05, seed=0
    )
    outputs = (
        TiltSeriesDataParserConfig(
            data=write_tilt_series(tmp_path, sim.projections, sim.angles_deg, sim.pixel_size_A, truth=truth)
        )
        .setup()
        .get_dataparser_outputs("train")
    )
    model = GaussianAtomsModelConfig(background="constant", psf_weights=(0.1, 0.05, 0.0)).setup(
        scene_box=outputs.scene_box, num_train_data=len(sim.angles_deg), metadata=outputs.metadata
    )
    # a floor of its own per view
    model.view_params["background"].data[:, 0] = torch.linspace(0.5, 1.5, len(sim.angles_deg))
    probes = model.means.detach()[:5] + 0.01, model.sigmas.detach()[:5]
    model.indexed_views = False  # each view through its own camera
    one_by_one, correlations = residuals.render_training_views(model), residuals.residual_correlations(model, *probes)
    model.indexed_views = True
    for size in (1, 100):
        monkeypatch.setattr(
            residuals, "view_chunks", lambda n, *_: [list(range(i, min(i + size, n))) for i in range(0, n, size)]
        )
        chunked = residuals.render_training_views(model)
        np.testing.assert_allclose(chunked, one_by_one, rtol=0, atol=2e-5 * np.abs(one_by_one).max())
        np.testing.assert_allclose(
            residuals.residual_correlations(model, *probes),
            correlations,
            rtol=1e-4,
            atol=1e-6 * np.abs(correlations).max(),
        )


def test_the_orthographic_camera_type_is_nerfstudios():
    """The engine reads cameras by their fields; its orthographic type is nerfstudio's."""
    from nerfstudio.cameras.cameras import CameraType

    assert R.ORTHOGRAPHIC_CAMERA == CameraType.ORTHOPHOTO.value


def _kernel_model(film: bool, weights=(0.4, 0.0, 0.04), psf="learned"):
    """What :func:`R.kernel_margin_px` and :func:`R.blur` read of a model: its kernel, its options
    and whether its volume reaches beyond the field (a film)."""
    from types import SimpleNamespace

    from gaussian_atoms_method.physics.psf import KERNEL_WIDTHS_A

    return SimpleNamespace(
        view_params={"psf": torch.tensor(weights, dtype=torch.float64)},
        psf_widths_host=KERNEL_WIDTHS_A,
        config=SimpleNamespace(psf=psf, psf_weights=weights),
        density=SimpleNamespace(field_half_extent=(10.0, 10.0, 5.0) if film else None),
    )


def test_an_atom_just_beyond_the_detector_reaches_into_it_through_the_kernel_on_a_film():
    from gaussian_atoms_method.physics.projector import project_gaussians
    from gaussian_atoms_method.physics.psf import widened

    pitch, h, w = 0.25, 40, 32
    rows = (torch.arange(h, dtype=torch.float64) - h / 2) * pitch
    cols = (torch.arange(w, dtype=torch.float64) - w / 2) * pitch
    # one atom 1.5 Å beyond the first column, one inside; the beam along z
    means = torch.tensor([[0.0, float(cols[0]) - 1.5, 0.0], [1.0, 0.5, 0.3]], dtype=torch.float64)
    sigmas, amps = torch.full((2,), 0.5, dtype=torch.float64), torch.full((2,), 100.0, dtype=torch.float64)
    axes = torch.tensor([[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]], dtype=torch.float64)

    def project(r, c):
        return project_gaussians(means, sigmas, amps, axes, r, c)

    # the reference: a detector 40 pixels wider on each side, blurred, cut back (float64)
    wide = R.blur(_kernel_model(True), project(widened(rows, 40, pitch), widened(cols, 40, pitch)), pitch)
    reference = wide[..., 40:-40, 40:-40]
    film = R.projected_and_blurred(_kernel_model(True), project, rows, cols, pitch)
    assert R.kernel_margin_px(_kernel_model(True), pitch) == 12  # three of the 1 Å width, in 0.25 Å pixels
    # a 3 Å margin leaves out only what the atom (1.5 Å out, 0.5 Å wide) projects beyond 3 Å out,
    # under 1% of its peak, and only its 4 Å share (0.04) carries that into the field
    edge = reference[..., :, :4]
    assert float((film - reference).abs().max()) < 1e-3 * float(edge.max())
    # without the margin (no film) the atom beyond the field is not seen: the edge misses its light
    alone = R.projected_and_blurred(_kernel_model(False), project, rows, cols, pitch)
    assert R.kernel_margin_px(_kernel_model(False), pitch) == 0
    assert float((alone - reference)[..., :, :4].abs().max()) > 0.5 * float(edge.max())  # 0.83
    # a kernel held at the identity needs no margin, and nothing lies beyond to blur in
    assert R.kernel_margin_px(_kernel_model(True, (0.0, 0.0, 0.0), psf="fixed"), pitch) == 0
