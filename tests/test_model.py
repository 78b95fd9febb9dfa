"""The nerfstudio layer: cameras from the dataparser, rendering, learned widths, atoms out."""

import math

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from dataparsers.tilt_series_dataparser import TiltSeriesDataParserConfig
from dataparsers.tilt_series_format import write_tilt_series
from gaussian_atoms_method.atoms.atom_set import AtomSet
from gaussian_atoms_method.nerfstudio_layer.launch import train_views
from gaussian_atoms_method.nerfstudio_layer.model import GaussianAtomsModelConfig
from gaussian_atoms_method.physics.geometry import detector_axes_from_tilts, pixel_centres
from gaussian_atoms_method.physics.projector import project_gaussians


def _series(tmp_path, tilt_axis="y", centre_px=None, shape=(30, 36)):
    rng = np.random.default_rng(0)
    angles = np.array([-50.0, -10.0, 25.0, 60.0])
    proj = rng.uniform(0, 10, size=(4,) + shape).astype(np.float32)
    write_tilt_series(
        tmp_path,
        proj,
        angles,
        0.3,
        truth=AtomSet(np.zeros((1, 3)), species=["Au"]),
        origin_A=(5.0, 6.0, 7.0),
        tilt_axis=tilt_axis,
        centre_px=centre_px,
    )
    return angles


def _model(tmp_path, **cfg):
    # These tests check rendering and training against full-resolution references from step 0;
    # the coarse phase (2 x 2-binned early steps, on by default) has its own test below.
    cfg.setdefault("coarse_steps", 0)
    # _series' projections are uniform noise on a level of 5: background auto would (rightly)
    # learn that level; these tests compare the atoms' rendering alone.
    cfg.setdefault("background", "none")
    outputs = TiltSeriesDataParserConfig(data=tmp_path).setup().get_dataparser_outputs("train")
    config = GaussianAtomsModelConfig(**cfg)
    model = config.setup(
        scene_box=outputs.scene_box, num_train_data=len(outputs.image_filenames), metadata=outputs.metadata
    )
    return model, outputs


def test_initial_mass_follows_the_backprojection(tmp_path):
    """init_mass="backprojection" shares the same measured mass as "equal" but in proportion to
    the smoothed back-projection: Gaussians that start on atoms carry several times the mass of
    those that start on noise, so the first prune removes the latter."""
    from gaussian_atoms_method.harness.simulate import parse_tilts, simulate_gaussian_tilt_series, spherical_particle
    from gaussian_atoms_method.physics.projector import gaussian_mass

    atoms = spherical_particle("Au", radius_A=6.0)
    sim = simulate_gaussian_tilt_series(atoms, parse_tilts("limited"), noise_std=20.0, seed=1)
    write_tilt_series(tmp_path, sim.projections, sim.angles_deg, sim.pixel_size_A, truth=atoms)
    masses = {}
    for init_mass in ("equal", "backprojection"):
        model, _ = _model(tmp_path, init_mass=init_mass, num_random=3 * len(atoms))
        masses[init_mass] = gaussian_mass(model.sigmas, model.amplitudes).double()
        on_atom = torch.as_tensor(cKDTree(atoms.positions).query(model.atoms().positions)[0] < 0.75)
    assert masses["backprojection"].sum().item() == pytest.approx(masses["equal"].sum().item(), rel=1e-5)
    assert torch.unique(masses["equal"]).numel() == 1
    weighted = masses["backprojection"]
    assert 0 < on_atom.sum() < len(on_atom) and weighted[on_atom].median() > 3 * weighted[~on_atom].median()


@pytest.mark.parametrize("tilt_axis, centre_px", [("y", None), ("x", (12.0, 20.5))])
def test_camera_rendering_matches_core_projector_in_A(tmp_path, tilt_axis, centre_px):
    """dataparser cameras + model rendering == core projector in Å with the README convention."""
    angles = _series(tmp_path, tilt_axis, centre_px)
    model, outputs = _model(tmp_path, num_random=5)
    norm = model.normalisation
    atoms = model.atoms()  # Å, truth frame
    axes = torch.tensor(detector_axes_from_tilts(angles, tilt_axis))
    h, w = 30, 36
    ci, cj = centre_px if centre_px is not None else ((h - 1) / 2, (w - 1) / 2)
    rows, cols = torch.tensor(pixel_centres(h, 0.3, ci)), torch.tensor(pixel_centres(w, 0.3, cj))
    t = lambda a: torch.tensor(a, dtype=torch.float64)
    expected = project_gaussians(
        t(atoms.positions - norm.origin_A), t(atoms.sigmas), t(atoms.amplitudes), axes, rows, cols
    )
    for v in range(len(angles)):
        got = model.get_outputs(outputs.cameras[v : v + 1])["projection"][..., 0].double() / norm.data_scale
        # float32 rendering vs float64 reference.
        torch.testing.assert_close(got, expected[v], rtol=1e-4, atol=1e-4 * float(expected[v].max()))


def test_width_is_learned(tmp_path):
    """Gradients reach sigma: one Gaussian started 40% too wide converges to the true width."""
    _series(tmp_path)
    model, outputs = _model(tmp_path, num_random=1, init="random")
    with torch.no_grad():
        model.gauss_params["means"].zero_()
    cams = outputs.cameras
    true_sigma = 0.02
    with torch.no_grad():
        # Start with 1.4x the width and half the peak (1.37x the mass).
        log_a = torch.full_like(model.gauss_params["log_amplitudes"], math.log(1500.0))
        model.gauss_params["log_sigmas"].fill_(math.log(true_sigma))
        model.gauss_params["log_amplitudes"].fill_(math.log(3000.0))
        target = [model.get_outputs(cams[v : v + 1])["projection"].detach() for v in range(4)]
        model.gauss_params["log_sigmas"].fill_(math.log(1.4 * true_sigma))
        model.gauss_params["log_amplitudes"].copy_(log_a)
    opt = torch.optim.Adam([model.gauss_params["log_sigmas"], model.gauss_params["log_amplitudes"]], lr=0.02)
    for step in range(400):
        opt.zero_grad()
        v = step % 4
        loss = model.get_loss_dict(model.get_outputs(cams[v : v + 1]), {"image": target[v]})["main_loss"]
        loss.backward()
        assert model.gauss_params["log_sigmas"].grad.abs().item() > 0 or loss.item() < 1e-3
        opt.step()
    assert float(model.sigmas.detach()[0]) == pytest.approx(true_sigma, rel=0.01)


def test_refinement_merges_and_prunes(tmp_path):
    _series(tmp_path)
    model, _ = _model(tmp_path, num_random=4, merge_threshold_A=0.5, init="random")
    ls = model.normalisation.length_scale
    with torch.no_grad():
        model.gauss_params["means"].copy_(torch.tensor([[0, 0, 0], [0.3 * ls, 0, 0], [0.2, 0.2, 0.2], [-0.2, 0, 0]]))
        model.gauss_params["log_amplitudes"][3] -= 10.0  # far too faint to be an atom
    mass = lambda: (model.amplitudes * (2 * math.pi * model.sigmas**2) ** 1.5).detach()
    mass_before = float(mass()[:2].sum())
    assert model.density.merge(model.gauss_params, model.optimizers) == 1 and model.num_points == 3
    assert float(mass()[0]) == pytest.approx(mass_before, rel=1e-5)
    assert model.density.prune(model.gauss_params, model.optimizers) == 1 and model.num_points == 2


def test_anisotropic_switch_renders_the_same_spheres(tmp_path):
    """With three equal widths, the ablation's anisotropic model renders exactly what the
    isotropic one does; gradients reach all three widths and the rotations."""
    _series(tmp_path)
    iso, outputs = _model(tmp_path, num_random=6, init="random")
    aniso, _ = _model(tmp_path, num_random=6, init="random", isotropic=False)
    assert aniso.gauss_params["log_sigmas"].shape == (6, 3) and aniso.gauss_params["quats"].shape == (6, 4)
    with torch.no_grad():
        aniso.gauss_params["means"].copy_(iso.gauss_params["means"])
        aniso.gauss_params["log_amplitudes"].copy_(iso.gauss_params["log_amplitudes"])
        aniso.gauss_params["log_sigmas"].copy_(iso.gauss_params["log_sigmas"].expand(6, 3))
    cam = outputs.cameras[1:2]
    a, b = iso.get_outputs(cam)["projection"], aniso.get_outputs(cam)["projection"]
    torch.testing.assert_close(b, a, rtol=1e-4, atol=1e-4 * float(a.max()))
    target = torch.rand_like(b) * float(b.max())
    aniso.get_loss_dict(aniso.get_outputs(cam), {"image": target})["main_loss"].backward()
    assert torch.all(aniso.gauss_params["log_sigmas"].grad.abs().sum(0) > 0)
    assert float(aniso.gauss_params["quats"].grad.abs().sum()) > 0
    # psf: the learned kernel
    assert set(aniso.get_param_groups()) == {
        "means",
        "log_sigmas",
        "log_amplitudes",
        "quats",
        "psf",
    }


def test_same_seed_same_atoms(tmp_path):
    """Deterministic on CPU: the same data and seed give bit-identical Gaussians, through
    densification, pruning and merging; another seed does not."""
    from gaussian_atoms_method.harness.simulate import parse_tilts, simulate_gaussian_tilt_series, spherical_particle

    atoms = spherical_particle("Au", radius_A=5.0)
    sim = simulate_gaussian_tilt_series(atoms, parse_tilts("limited")[::10], noise_std=20.0, seed=1)
    write_tilt_series(tmp_path, sim.projections, sim.angles_deg, sim.pixel_size_A, truth=atoms)
    cfg = dict(
        num_random=300,
        init="random",
        warmup_length=24,
        refine_every=4,
        merge_every=4,
        stop_split_at=32,
        densify_grad_thresh=0.01,
    )
    runs = []
    for seed in (3, 3, 4):
        model, outputs = _model(tmp_path, seed=seed, **cfg)
        targets = [outputs.metadata["projections"][v][..., None] for v in range(len(sim.angles_deg))]
        train_views(model, outputs.cameras, targets, steps=40)
        runs.append(model.atoms())
    assert 0 < len(runs[0]) == len(runs[1])
    np.testing.assert_array_equal(runs[0].positions, runs[1].positions)
    np.testing.assert_array_equal(runs[0].amplitudes, runs[1].amplitudes)
    assert len(runs[0]) != len(runs[2]) or not np.array_equal(runs[0].positions, runs[2].positions)


def test_divergence_stops_with_the_step_and_cause(tmp_path):
    """A non-finite parameter stops training with a message naming the step and the cause."""
    _series(tmp_path)
    model, outputs = _model(tmp_path, num_random=5, init="random")
    model.step = 17
    with torch.no_grad():
        model.gauss_params["means"][2, 0] = float("nan")
    target = outputs.metadata["projections"][0][..., None]
    with pytest.raises(
        FloatingPointError, match=r"step 17: the loss is .* cause: 1 Gaussian\(s\) with non-finite means"
    ):
        model.get_loss_dict(model.get_outputs(outputs.cameras[0:1]), {"image": target})


def test_parameters_are_kept_in_range(tmp_path):
    """Widths stay within [min_sigma_A, max_sigma_A] and amplitudes finite whatever the optimiser does."""
    _series(tmp_path)
    model, _ = _model(tmp_path, num_random=3, init="random", min_sigma_A=0.2, max_sigma_A=4.0)
    with torch.no_grad():
        model.gauss_params["log_sigmas"][0] = 50.0
        model.gauss_params["log_sigmas"][1] = -50.0
        model.gauss_params["log_amplitudes"][2] = 1e4
        model.gauss_params["means"][2] = 1e6
    model.refine_after_step(1)
    sig_A = model.atoms().sigmas
    assert sig_A[0] == pytest.approx(4.0, rel=1e-5) and sig_A[1] == pytest.approx(0.2, rel=1e-5)
    assert torch.isfinite(model.amplitudes).all() and float(model.means.abs().max()) <= 1.0


def test_a_translation_of_the_object_leaves_the_shifts_at_zero():
    """The gauge: shifts of the form ``P_v t`` (a translation ``t`` of the object seen in each
    view) are no view's own, for single-axis tilts and Euler views alike; a gauge-free shift is
    left as it is.  A shift the same in every view along the rows is not a translation: over
    +-70 degrees a move along x (cos theta, 0.34-1) takes most of it, and the rest, the tilt axis
    off centre (a fifth to a quarter of it here), stays."""
    from gaussian_atoms_method.atoms.view_prediction import gauge_free_shifts
    from gaussian_atoms_method.physics.geometry import detector_axes_from_euler, detector_axes_from_tilts

    rng = np.random.default_rng(3)
    euler = np.c_[rng.uniform(-1, 1, 30), np.linspace(-63, 56, 30), rng.uniform(-1, 1, 30)]
    for axes in (detector_axes_from_tilts(np.linspace(-70, 70, 41)), detector_axes_from_euler(euler, "zyx")):
        axes = torch.as_tensor(axes[:, :2])
        translation = axes @ torch.tensor([0.4, -0.7, 1.3], dtype=torch.float64)
        assert float(gauge_free_shifts(translation, axes).abs().max()) < 1e-12
        free = gauge_free_shifts(torch.as_tensor(rng.normal(size=(len(axes), 2))), axes)
        torch.testing.assert_close(gauge_free_shifts(free + translation, axes), free)
        off_axis = torch.zeros(len(axes), 2, dtype=torch.float64)
        off_axis[:, 0] = 0.5
        assert float(gauge_free_shifts(off_axis, axes).norm()) > 0.15 * float(off_axis.norm())


def test_view_shifts_and_background_are_recovered(tmp_path):
    """Per-view in-plane shifts (up to 1 Å) and a constant background per view are learned
    back from simulated data when the atoms are known (the backgrounds in closed form,
    :mod:`gaussian_atoms_method.engine.floors`): shifts to 0.05 Å,
    backgrounds to 1% of the projection peak (they are 5-20% of it) (L1, 600 steps: a fifth of a 0.25 Å pixel is
    sub-pixel
    registration, what alignment needs for pm atoms)."""
    from scipy import ndimage

    from gaussian_atoms_method.harness.simulate import simulate_gaussian_tilt_series, spherical_particle

    atoms = spherical_particle("Au", radius_A=4.0)
    angles = np.linspace(-60, 60, 9)
    sim = simulate_gaussian_tilt_series(atoms, angles, noise_std=0.0)
    rng = np.random.default_rng(5)
    # shifts a translation of the particle makes are no view's (gauge_free_shifts): the drawn ones are
    # kept free of them, and the learned ones read through the same function
    from gaussian_atoms_method.atoms.view_prediction import gauge_free_shifts
    from gaussian_atoms_method.physics.geometry import detector_axes_from_tilts

    axes = torch.as_tensor(detector_axes_from_tilts(angles)[:, :2])
    shifts_A = gauge_free_shifts(torch.as_tensor(rng.uniform(-1, 1, size=(len(angles), 2))), axes).numpy()
    backgrounds = rng.uniform(0.05, 0.2, size=len(angles)) * sim.projections.max()
    proj = np.stack(
        [ndimage.shift(p, s / sim.pixel_size_A, order=3) + b for p, s, b in zip(sim.projections, shifts_A, backgrounds)]
    )
    write_tilt_series(tmp_path, proj.astype(np.float32), angles, sim.pixel_size_A, truth=sim.truth)
    model, outputs = _model(
        tmp_path, num_random=len(atoms), init="random", refine_alignment=True, background="constant", loss="l1"
    )
    norm = model.normalisation
    with torch.no_grad():
        model.gauss_params["means"].copy_(torch.as_tensor(norm.positions_from_A(atoms.positions), dtype=torch.float32))
        model.gauss_params["log_sigmas"].fill_(math.log(sim.truth.sigmas[0] * norm.length_scale))
    # Known positions and widths; amplitudes and shifts learned jointly, the backgrounds solved every refine_every
    # steps.
    opt = torch.optim.Adam(
        [
            {"params": [model.view_params["view_shifts"]], "lr": 2e-3},
            {"params": [model.gauss_params["log_amplitudes"]], "lr": 2e-2},
        ]
    )
    targets = [outputs.metadata["projections"][v][..., None] for v in range(len(angles))]
    for step in range(600):
        opt.zero_grad()
        v = step % len(angles)
        loss = model.get_loss_dict(model.get_outputs(outputs.cameras[v : v + 1]), {"image": targets[v]})["main_loss"]
        loss.backward()
        opt.step()
        model.floors.decide(model, step + 1)
    s = model.view_params["view_shifts"].detach().double()
    learned_A = gauge_free_shifts(s, axes).numpy() / norm.length_scale
    assert np.abs(learned_A - shifts_A).max() < 0.05
    learned_bg = model.view_params["background"].detach().double().numpy()[:, 0] / norm.data_scale
    np.testing.assert_allclose(learned_bg, backgrounds, rtol=0, atol=0.01 * sim.projections.max())


def test_tilt_offsets_are_recovered(tmp_path, fit_view_parameter):
    """Projections taken at angles off their nominal values by up to 0.5 deg (goniometer
    error), atoms known: the learned per-view offsets match the errors (mean removed) to
    0.05 deg.  A tilt error moves an atom by its distance from the axis times the angle: the
    16 atoms sit 8-10 Å out, where 0.5 deg is 0.08 Å and 0.05 deg 8 pm."""
    from gaussian_atoms_method.atoms.atom_set import AtomSet
    from gaussian_atoms_method.harness.simulate import simulate_gaussian_tilt_series

    rng = np.random.default_rng(7)
    directions = rng.normal(size=(16, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    atoms = AtomSet(directions * rng.uniform(8, 10, (16, 1)), species=["Au"] * 16)
    angles = np.linspace(-60, 60, 9)
    errors = np.random.default_rng(6).uniform(-0.5, 0.5, len(angles))
    errors -= errors.mean()
    sim = simulate_gaussian_tilt_series(atoms, angles + errors, noise_std=0.0)
    write_tilt_series(tmp_path, sim.projections.astype(np.float32), angles, sim.pixel_size_A, truth=sim.truth)
    model, outputs = _model(tmp_path, num_random=len(atoms), init="random", refine_tilts=True)
    t = fit_view_parameter(model, outputs, atoms, sim, "view_tilts", 1e-3, 900).double().numpy()[:, 0]
    learned_deg = np.rad2deg(t - t.mean())
    np.testing.assert_allclose(learned_deg, errors, atol=0.05)


def test_view_gains_are_recovered_with_their_mean_taken_out(tmp_path, fit_view_parameter):
    """Projections whose views were taken at gains 7% RMS apart (the Ta film's scatter), atoms
    known: the learned gains match them to 1% once the mean of each is taken out (a gain the
    same in every view is the amplitudes' scale, learned with them).  Noise-free: what is left
    is the optimiser's, a tenth of the scatter."""
    from gaussian_atoms_method.engine.rendering import view_gain
    from gaussian_atoms_method.harness.simulate import simulate_gaussian_tilt_series, spherical_particle

    atoms = spherical_particle("Au", radius_A=4.0)
    angles = np.linspace(-60, 60, 9)
    sim = simulate_gaussian_tilt_series(atoms, angles, noise_std=0.0)
    log_gains = np.random.default_rng(3).normal(0.0, 0.07, len(angles))
    write_tilt_series(
        tmp_path, (sim.projections * np.exp(log_gains)[:, None, None]).astype(np.float32), angles, sim.pixel_size_A
    )
    model, outputs = _model(tmp_path, num_random=len(atoms), init="random", refine_gain=True)
    g = fit_view_parameter(model, outputs, atoms, sim, "view_gains", 2e-3, 900).double()
    learned = np.array([float(view_gain(g, v)) for v in range(len(angles))])
    np.testing.assert_allclose(learned, np.exp(log_gains - log_gains.mean()), rtol=0.01)


def test_viewer_finds_the_atoms_and_renders_a_perspective_camera(tmp_path):
    """nerfstudio's viewer reads every property of the model (splatfacto's included) and finds
    custom controls by walking it: that must work, find the atom point cloud, and a viewer
    (perspective) camera must render the orthographic projection along its view direction at
    its magnification at the tilt centre, with a depth map behind everything."""
    from nerfstudio.cameras.cameras import Cameras, CameraType
    from nerfstudio.viewer.utils import parse_object
    from nerfstudio.viewer.viewer_elements import ViewerControl

    from gaussian_atoms_method.nerfstudio_layer.viewer import AtomsInViewer, mass_colours

    _series(tmp_path)
    model, outputs = _model(tmp_path, num_random=20)
    controls = [c for _, c in parse_object(model, ViewerControl, "Custom Elements")]
    assert len(controls) == 1 and isinstance(controls[0], AtomsInViewer)
    positions, masses, size = model._viewer_atoms()
    assert positions.shape == (model.num_points, 3) and masses.shape == (model.num_points,) and size > 0
    assert model.colors.shape == (model.num_points, 3) and model.quats.shape == (model.num_points, 4)
    controls[0].refresh()  # no viewer yet: a no-op, not an error
    colours = mass_colours(np.array([0.0, 1.0, 2.0, 2.0]))
    assert colours.dtype == np.uint8 and colours[0].sum() < colours[-1].sum()  # heavier = brighter

    ortho = outputs.cameras[1:2]
    distance = 2.5  # world units from the tilt centre, looking back along the same axis
    c2w = ortho.camera_to_worlds.clone()
    c2w[0, :, 3] = c2w[0, :, 2] * distance
    f = ortho.fx[0, 0] * distance  # the perspective focal length with the same magnification there
    persp = Cameras(
        camera_to_worlds=c2w,
        fx=f,
        fy=f,
        cx=ortho.cx[0, 0],
        cy=ortho.cy[0, 0],
        width=ortho.width[0, 0],
        height=ortho.height[0, 0],
        camera_type=CameraType.PERSPECTIVE,
    )
    ortho_out, persp_out = model.get_outputs(ortho), model.get_outputs(persp)
    torch.testing.assert_close(persp_out["projection"], ortho_out["projection"], rtol=1e-4, atol=1e-3)
    assert persp_out["depth"].shape == persp_out["projection"].shape and float(persp_out["depth"].min()) > 100
    assert list(persp_out)[0] == "rgb"  # the viewer shows the first output


def test_the_stop_judges_steps_in_the_residual_that_is_there(tmp_path):
    """The precision the stop judges by reads the residual's level and its weight at the atoms'
    scale (a grainy misfit moves a position more than white noise of its level): the white
    bound's noise times the position template's factor, and the bound with it (it is linear in
    the noise)."""
    from gaussian_atoms_method.atoms.information import residual_spectrum_factors
    from gaussian_atoms_method.engine.results import residual_noise
    from gaussian_atoms_method.engine.stopping import atom_scale_noise

    _series(tmp_path)
    model, _ = _model(tmp_path, num_random=30, init="random")
    atoms = model.atoms()
    white, level = model.position_std_A(atoms)
    noise, amplitude_noise = atom_scale_noise(model, atoms)
    grain, _ = model.position_std_A(atoms, noise)
    _, residuals, _ = residual_noise(model)
    sigma_px = float(np.median(atoms.sigmas)) / model.view_set.pixel_size_A
    factors = residual_spectrum_factors(residuals / model.normalisation.data_scale, level, sigma_px)
    assert min(factors) > 0 and noise == pytest.approx(level * factors[0], rel=1e-9)
    assert amplitude_noise == pytest.approx(level * factors[1], rel=1e-9)
    np.testing.assert_allclose(grain, white * factors[0], rtol=1e-6)


def test_convergence_stop_needs_settled_atoms(tmp_path):
    """The early stop fires only after two refine intervals in a row in which the Gaussian
    count held and the positions moved (RMS) less than the atoms' noise-limited precision;
    a move or a change of count starts the count again."""
    _series(tmp_path)
    model, _ = _model(tmp_path, num_random=30, init="random", warmup_length=100, refine_every=100)
    assert not model.converged(50)  # not a check step
    assert not model.converged(100)  # first check: nothing to compare with
    assert not model.converged(200)  # settled once
    assert model.converged(300)  # settled twice
    from gaussian_atoms_method.engine.stopping import atom_scale_noise

    atoms = model.atoms()
    std_A, _ = model.position_std_A(atoms, atom_scale_noise(model, atoms)[0])  # what the check judges by
    precision_A = float(np.median(np.sqrt((std_A**2).sum(axis=1))))
    with torch.no_grad():  # every atom moves by three times the precision
        model.gauss_params["means"][:, 0] += 3 * precision_A * model.normalisation.length_scale
    assert not model.converged(400)
    assert not model.converged(500) and model.converged(600)
    from gaussian_atoms_method.density.remap import keep_remap

    keep = torch.ones(model.num_points, dtype=torch.bool)
    keep[0] = False
    # one Gaussian fewer, as a prune makes it: the set changed
    model.density.remap(model.gauss_params, model.optimizers, *keep_remap(keep))
    assert not model.converged(700) and not model.converged(800) and model.converged(900)


def test_coarse_phase_renders_and_compares_2x2_blocks(tmp_path):
    """During the coarse steps a training view renders at the centres of 2 x 2 pixel blocks
    and the loss bins the measurement alike; afterwards (and in evaluation) full resolution.
    A block's mean and the value at its centre differ by the curvature over the block (Gaussians
    of 2-3 pixels here: a few percent of the peak at most)."""
    import torch.nn.functional as F

    _series(tmp_path)  # 30 x 36 pixels
    # the binning, in the simplest term
    model, outputs = _model(tmp_path, num_random=20, coarse_steps=100, init_sigma_A=0.7, loss="l1")
    camera, gt = outputs.cameras[0:1], outputs.metadata["projections"][0][..., None]
    model.train()
    model.step = 0
    coarse = model.get_outputs(camera)
    assert coarse["projection"].shape == (15, 18, 1) and coarse["rgb"].shape == (15, 18, 3)
    model.eval()
    full = model.get_outputs(camera)["projection"]
    assert full.shape == (30, 36, 1)
    pooled = F.avg_pool2d(full[..., 0][None, None], 2)[0, 0]
    peak = float(full.max())
    assert float((coarse["projection"][..., 0] - pooled).abs().max()) < 0.05 * peak
    model.train()
    loss = model.get_loss_dict(coarse, {"image": gt})["main_loss"]
    binned = F.avg_pool2d(gt[..., 0][None, None], 2)[0, 0]
    torch.testing.assert_close(loss, (coarse["projection"][..., 0] - binned).abs().mean())
    model.step = 100
    assert model.get_outputs(camera)["projection"].shape == (30, 36, 1)


def test_views_per_step_fits_several_views_in_one_loss(tmp_path):
    """views_per_step=3: the camera's view and two other distinct views rendered in one call;
    the loss is the mean L1 over the three views, equal to rendering each alone.  Coarse steps
    bin the extra views too.  Per-view parameters cannot be batched: refused, option named."""
    _series(tmp_path)
    model, outputs = _model(tmp_path, num_random=20, views_per_step=3, loss="l1")
    single, _ = _model(tmp_path, num_random=20)  # same seed: the same start
    projections = outputs.metadata["projections"]
    model.train()
    out = model.get_outputs(outputs.cameras[1:2])
    views = [1] + out["extra_views"].tolist()
    assert out["extra_projection"].shape == (2, 30, 36, 1) and len(set(views)) == 3
    loss = model.get_loss_dict(out, {"image": projections[1][..., None]})["main_loss"]
    single.eval()
    per_view = [
        (single.get_outputs(outputs.cameras[v : v + 1])["projection"][..., 0] - projections[v]).abs().mean()
        for v in views
    ]
    torch.testing.assert_close(loss, torch.stack(per_view).mean(), rtol=1e-5, atol=0)

    coarse, _ = _model(tmp_path, num_random=20, views_per_step=3, coarse_steps=100)
    coarse.train()
    out = coarse.get_outputs(outputs.cameras[0:1])
    assert out["projection"].shape == (15, 18, 1) and out["extra_projection"].shape == (2, 15, 18, 1)
    assert torch.isfinite(coarse.get_loss_dict(out, {"image": projections[0][..., None]})["main_loss"])

    # A background is per view but adds after the projector: batched views each get their own.
    bg, _ = _model(tmp_path, num_random=20, views_per_step=3, background="constant")
    bg.view_params["background"].data[:, 0] = torch.arange(4.0)
    bg.train()
    out = bg.get_outputs(outputs.cameras[1:2])
    for image, v in zip(out["extra_projection"], out["extra_views"].tolist()):
        bg.eval()
        alone = bg.get_outputs(outputs.cameras[v : v + 1])["projection"]
        bg.train()
        torch.testing.assert_close(image, alone, rtol=1e-5, atol=1e-4)
    for option in ({"refine_alignment": True}, {"refine_gain": True}, {"isotropic": False}):
        with pytest.raises(ValueError, match="views-per-step 2 cannot be combined"):
            _model(tmp_path, num_random=20, views_per_step=2, **option)


def test_built_model_loads_checkpoints_with_numpy_scalars(tmp_path):
    """nerfstudio's schedulers leave numpy scalars in every checkpoint; torch >= 2.6 loads with
    weights_only=True.  Building the model (as nerfstudio does before loading) allows them."""
    _series(tmp_path)
    _model(tmp_path, num_random=3, init="random")
    path = tmp_path / "step.ckpt"
    torch.save({"lr": np.float64(1e-3), "dtype": np.dtype("float32")}, path)
    assert torch.load(path, weights_only=True)["lr"] == pytest.approx(1e-3)


def test_a_smooth_floor_loads_a_checkpoint_saved_with_one_background_term(tmp_path):
    """Runs saved before the smooth floor learned its quadratic correction hold one background
    term a view; they load with the correction at zero (the fixed frame surface they had)."""
    _series(tmp_path)
    model, _ = _model(tmp_path, num_random=3, init="random", background="smooth")
    assert model.view_params["background"].shape == (4, 6)
    state = model.state_dict()
    old = {**state, "view_params.background": torch.arange(4.0)[:, None]}
    model.view_params["background"].data.fill_(7.0)
    model.load_state_dict(old)
    torch.testing.assert_close(
        model.view_params["background"].data, torch.cat([torch.arange(4.0)[:, None], torch.zeros(4, 5)], dim=1)
    )
