"""Views held out of a fit: split, predicted as the run renders them, scored; a kernel held fixed."""

import numpy as np
import pytest
import torch

from gaussian_atoms_method.atoms.atom_set import AtomSet


def _series(tmp_path, n_views=6, shape=(40, 36)):
    from dataparsers.tilt_series_format import load_tilt_series, write_tilt_series

    rng = np.random.default_rng(0)
    angles = np.linspace(-60, 60, n_views)
    # Off-centre tilt centre and a non-zero origin: both conventions are exercised.
    path = write_tilt_series(
        tmp_path / "series",
        rng.normal(size=(n_views, *shape)).astype(np.float32),
        angles,
        0.4,
        truth=AtomSet(positions=np.zeros((1, 3)) + 2.0, species=np.array(["Au"])),
        origin_A=(1.0, -2.0, 0.5),
        centre_px=(18.0, 20.0),
    )
    return load_tilt_series(path)


def test_held_out_views_are_predicted_as_the_run_renders_them(tmp_path):
    """Three Gaussians set in the model: :func:`predicted_views` of ``model.atoms()`` (Å, the
    output frame, physical amplitudes) equals the model's own rendering of every view, brought
    back to input units, to 1e-4 of its peak (the model renders in float32), with and without a
    kernel (the kernel's weights set in the model alike)."""
    from dataparsers.tilt_series_dataparser import TiltSeriesDataParserConfig
    from gaussian_atoms_method.atoms.view_prediction import predicted_views
    from gaussian_atoms_method.nerfstudio_layer.model import GaussianAtomsModelConfig

    series = _series(tmp_path)
    outputs = TiltSeriesDataParserConfig(data=tmp_path / "series").setup().get_dataparser_outputs("train")
    model = GaussianAtomsModelConfig(num_random=3, init="random", coarse_steps=0, background="none", loss="l2").setup(
        scene_box=outputs.scene_box, num_train_data=len(outputs.image_filenames), metadata=outputs.metadata
    )
    norm = model.normalisation
    positions_A = np.array([[1.0, -2.0, 0.5], [3.5, 0.0, -1.0], [-2.0, -4.0, 2.5]])
    with torch.no_grad():
        model.gauss_params["means"].copy_(torch.as_tensor(norm.positions_from_A(positions_A), dtype=torch.float32))
        model.gauss_params["log_sigmas"].copy_(torch.log(torch.tensor([[0.5], [0.7], [0.6]]) * norm.length_scale))
        model.gauss_params["log_amplitudes"].copy_(torch.log(torch.tensor([[20.0], [10.0], [15.0]])))
    model.eval()
    for weights in ([0.0, 0.0, 0.0], [0.0, 0.2, 0.1]):
        with torch.no_grad():
            model.view_params["psf"].copy_(torch.tensor(weights))
            rendered = (
                torch.stack(
                    [
                        model.get_outputs(outputs.cameras[v : v + 1])["projection"][..., 0]
                        for v in range(len(series.angles_deg))
                    ]
                )
                .double()
                .numpy()
            )
        predicted = predicted_views(model.atoms(), series, weights)
        assert np.abs(predicted - rendered / norm.data_scale).max() < 1e-4 * np.abs(predicted).max()


def test_an_atom_just_beyond_the_field_sends_its_kernel_tails_into_the_predicted_views(tmp_path):
    """An atom 1 Å beyond the detector's edge, through a kernel with weight at 2 and 4 Å: the
    views predicted on the detector equal those predicted on one 40 pixels wider each side and cut
    back (the kernel's reach there is far inside), to 1e-3 of the peak (the kernel's 4 Å tails
    beyond the 3 Å margin hold about 1e-3 of it); without the margin the edge would miss it."""
    import copy

    from gaussian_atoms_method.atoms.view_prediction import predicted_views

    series = _series(tmp_path)
    h, w = series.projections.shape[1:]
    edge_A = (w - 1 - series.centre_px[1]) * series.pixel_size_A  # the last column, along the tilt axis (y)
    atoms = AtomSet(
        positions=np.array([[0.0, edge_A + 1.0, 0.0]]) + np.asarray(series.origin_A),
        sigmas=np.array([0.5]),
        amplitudes=np.array([40.0]),
    )
    pad = 40
    wide = copy.copy(series)
    wide.projections = np.zeros((len(series.angles_deg), h + 2 * pad, w + 2 * pad), np.float32)
    wide.centre_px = (series.centre_px[0] + pad, series.centre_px[1] + pad)
    kernel = [0.0, 0.3, 0.3]
    reference = predicted_views(atoms, wide, kernel)[:, pad : pad + h, pad : pad + w]
    predicted = predicted_views(atoms, series, kernel)
    peak = np.abs(reference).max()
    assert np.abs(reference[:, :, -1]).max(axis=1).min() > 0.5 * peak  # every view's edge sees the atom
    assert np.abs(predicted - reference).max() < 1e-3 * peak


def test_held_out_rms_reads_the_noise_when_the_atoms_and_kernel_are_right(tmp_path):
    """Data = three Gaussians through a kernel with 30% in its tails + a per-view offset + white
    noise of 0.5: scored with the right atoms and kernel, the held-out rms is the noise (to 3%:
    about 8,600 pixels, the standard error of an rms is 0.8%); without the kernel, larger; split
    views keep their angles, geometry and truth."""
    from dataparsers.tilt_series_format import load_tilt_series
    from gaussian_atoms_method.atoms.view_prediction import held_out_rms, predicted_views
    from gaussian_atoms_method.harness.held_out import split_views

    series = _series(tmp_path)
    atoms = AtomSet(
        positions=np.array([[1.0, -2.0, 0.5], [3.5, 0.0, -1.0], [-2.0, -4.0, 2.5]]),
        sigmas=np.array([0.5, 0.7, 0.6]),
        amplitudes=np.array([40.0, 30.0, 35.0]),
    )
    kernel = [0.0, 0.2, 0.1]
    rng = np.random.default_rng(1)
    series.projections = (
        predicted_views(atoms, series, kernel)
        + np.arange(len(series.angles_deg))[:, None, None]
        + rng.normal(scale=0.5, size=series.projections.shape)
    ).astype(np.float32)
    assert held_out_rms(atoms, series, kernel) == pytest.approx(0.5, rel=0.03)
    assert held_out_rms(atoms, series, None) > 1.2 * held_out_rms(atoms, series, kernel)
    even, odd = split_views(series, tmp_path / "views")
    for path, start in ((even, 0), (odd, 1)):
        part = load_tilt_series(path)
        assert np.allclose(part.angles_deg, series.angles_deg[start::2]) and np.array_equal(
            part.projections, series.projections[start::2]
        )
        assert (
            np.allclose(part.centre_px, series.centre_px)
            and np.allclose(part.origin_A, series.origin_A)
            and part.truth_path is not None
        )
    # a series with Euler angles (RESIRE's Z-Y-X) keeps them, and their convention, in each half
    euler = np.stack(
        [np.full_like(series.angles_deg, 0.3), series.angles_deg, -0.2 * np.ones_like(series.angles_deg)], 1
    )
    series.euler_deg, series.euler_convention = euler, "zyx"
    for path, start in zip(split_views(series, tmp_path / "euler"), (0, 1)):
        part = load_tilt_series(path)
        assert part.euler_convention == "zyx" and np.allclose(part.euler_deg, euler[start::2])


def test_a_fixed_kernel_is_held_and_bad_weights_are_named(tmp_path):
    """``--pipeline.model.psf fixed``: the kernel is the given weights and takes no gradient;
    ``learned`` starts from them; weights that are not a non-negative kernel are refused with the
    option's name."""
    from dataparsers.tilt_series_dataparser import TiltSeriesDataParserConfig
    from gaussian_atoms_method.engine.errors import OptionError
    from gaussian_atoms_method.nerfstudio_layer.model import GaussianAtomsModelConfig
    from gaussian_atoms_method.nerfstudio_layer.options import GaussianAtomsOptions

    _series(tmp_path)
    outputs = TiltSeriesDataParserConfig(data=tmp_path / "series").setup().get_dataparser_outputs("train")
    for mode in ("fixed", "learned"):
        model = GaussianAtomsModelConfig(
            num_random=3, init="random", coarse_steps=0, background="none", psf=mode, psf_weights=(0.0, 0.15, 0.2)
        ).setup(scene_box=outputs.scene_box, num_train_data=len(outputs.image_filenames), metadata=outputs.metadata)
        psf = model.view_params["psf"]
        assert torch.allclose(psf.detach(), torch.tensor([0.0, 0.15, 0.2])) and psf.requires_grad == (mode == "learned")
    for weights in ((0.5, 0.6, 0.0), (-0.1, 0.0, 0.0)):
        with pytest.raises(OptionError, match="psf-weights"):
            GaussianAtomsOptions(psf_weights=weights).check()


def _three_atoms_in_halves(tmp_path):
    """Three atoms (two 2.6 Å apart) and their noise-free views, split into even and odd views."""
    from dataparsers.tilt_series_format import load_tilt_series
    from gaussian_atoms_method.atoms.view_prediction import predicted_views
    from gaussian_atoms_method.harness.held_out import split_views

    series = _series(tmp_path, n_views=8)
    truth = AtomSet(
        positions=np.array([[0.0, 0.0, 0.0], [2.6, 0.0, 0.0], [-3.0, 3.0, 1.0]]),
        sigmas=np.array([0.5, 0.5, 0.5]),
        amplitudes=np.array([40.0, 40.0, 40.0]),
    )
    series.projections = predicted_views(truth, series).astype(np.float32)
    even, odd = (load_tilt_series(p) for p in split_views(series, tmp_path / "views"))
    return truth, even, odd


def test_merge_costs_keep_a_demanded_pair_and_drop_a_split_atom(tmp_path):
    """Noise-free views of two atoms 2.6 Å apart, split into even and odd views.  Read as two
    Gaussians (the truth), merging them costs on both halves, in proportion to the views each
    holds (to 25%: the halves see the pair at different angles).  An atom read as two halves of
    its mass 0.2 Å apart is better merged on both halves (the merged Gaussian is the atom), by
    far less than the real pair costs."""
    from gaussian_atoms_method.harness.held_out import pair_merge_costs

    truth, even, odd = _three_atoms_in_halves(tmp_path)
    costs = pair_merge_costs(truth, np.array([[0, 1]]), even, odd)[0]
    assert costs[0] > 0 and costs[1] == pytest.approx(costs[0], rel=0.25)

    halves = AtomSet(
        positions=np.array([[2.5, 0.0, 0.0], [2.7, 0.0, 0.0], [0.0, 0.0, 0.0], [-3.0, 3.0, 1.0]]),
        sigmas=np.full(4, 0.5),
        amplitudes=np.array([20.0, 20.0, 40.0, 40.0]),
    )
    split = pair_merge_costs(halves, np.array([[0, 1]]), even, odd)[0]
    assert np.all(split < 0) and np.all(-split < 0.01 * costs.min())


def test_move_costs_find_the_place_the_unseen_views_say(tmp_path):
    """Noise-free views of three atoms, split into even and odd views.  Moving a true atom 1 Å
    along the beam costs on both halves; moving an atom placed 1 Å off back to its place gains on
    both, by the same amount (the cost is the difference of two squared distances from the data)."""
    from gaussian_atoms_method.harness.held_out import move_costs

    truth, even, odd = _three_atoms_in_halves(tmp_path)
    away = truth.positions[1] + np.array([0.0, 0.0, 1.0])
    costs = move_costs(truth, np.array([1]), away[None], even, odd)[0]
    assert np.all(costs > 0)

    off = AtomSet(positions=truth.positions.copy(), sigmas=truth.sigmas, amplitudes=truth.amplitudes)
    off.positions[1] = away
    back = move_costs(off, np.array([1]), truth.positions[1:2], even, odd)[0]
    # float32 views: the perfect fit's residual is rounding, 1e-6 of the cost
    np.testing.assert_allclose(back, -costs, rtol=1e-4)


def test_a_held_out_views_own_shift_and_gain_are_found():
    """``best_registration``: a view moved by a known sub-pixel shift, scaled by a gain of 1.07
    (the Ta film's scatter between views) and raised by a constant is taken back onto its
    prediction to a hundredth of a pixel and 1e-3 in gain (cubic interpolation of a 2 px wide
    peak)."""
    from scipy import ndimage

    from gaussian_atoms_method.atoms.view_prediction import best_registration

    rows, cols = np.meshgrid(np.arange(40.0), np.arange(36.0), indexing="ij")
    predicted = np.exp(-((rows - 18.2) ** 2 + (cols - 17.6) ** 2) / 8.0) + 0.5 * np.exp(
        -((rows - 25.0) ** 2 + (cols - 10.0) ** 2) / 8.0
    )
    measured = 1.07 * ndimage.shift(predicted, (0.3, -0.7), order=3, mode="nearest") + 0.2
    shift, gain = best_registration(measured, predicted)
    np.testing.assert_allclose(shift, [0.3, -0.7], atol=0.01)
    assert gain == pytest.approx(1.07, abs=1e-3)


def _blobs(n_views: int, seed: int) -> np.ndarray:
    """(V, 64, 64) views of 40 Gaussian peaks 2 px wide, laid out at random."""
    rng = np.random.default_rng(seed)
    rows, cols = np.meshgrid(np.arange(64.0), np.arange(64.0), indexing="ij")
    centres = rng.uniform(8, 56, size=(40, 2))
    one = sum(np.exp(-((rows - r) ** 2 + (cols - c) ** 2) / 8.0) for r, c in centres)
    return np.repeat(one[None], n_views, axis=0)


def test_the_shifts_a_residual_holds_are_read_and_the_halves_of_the_views_agree_on_them():
    """``residual_shifts``: views moved by known shifts (up to 0.3 px; cubic interpolation) under
    noise of a thousandth of a peak give each shift back to 0.03 px (one Gauss-Newton step:
    the neglected curvature and the central difference's 4% on a 2 px peak), and the halves of
    the views agree on them far beyond 3 standard errors; noise alone gives shifts of no
    agreement (within 3); a translation of the object (``P_v t``) is no view's shift."""
    from scipy import ndimage

    from gaussian_atoms_method.atoms.view_prediction import residual_shifts
    from gaussian_atoms_method.physics.geometry import detector_axes_from_tilts

    rng = np.random.default_rng(1)
    predicted = _blobs(30, 0)
    noise = lambda: rng.normal(0, 1e-3, predicted.shape)  # noqa: E731
    moved = lambda shifts: np.stack([ndimage.shift(p, s, order=3, mode="nearest") for p, s in zip(predicted, shifts)])  # noqa: E731
    shifts = rng.uniform(-0.3, 0.3, size=(30, 2))
    found, z = residual_shifts(moved(shifts) + noise() - predicted, predicted)
    np.testing.assert_allclose(found, shifts, atol=0.03)
    assert z > 6
    _, z_noise = residual_shifts(noise(), predicted)
    assert abs(z_noise) < 3
    axes = detector_axes_from_tilts(np.linspace(-60, 60, 30))[:, :2]
    translation = axes @ np.array([0.2, -0.1, 0.3])  # (V, 2) px, a pixel of 1 Å
    found, _ = residual_shifts(moved(translation) + noise() - predicted, predicted, axes)
    assert np.abs(found).max() < 0.03


def test_the_kernel_a_run_ended_with_is_read_from_its_psf_json(tmp_path):
    """``held-out-views``' candidates: a learned kernel is the one the run wrote (``psf.json``),
    a held one its given weights; a run that wrote none held no kernel."""
    import json

    from gaussian_atoms_method.harness.kernel_choice import kernel_of_run

    assert kernel_of_run(tmp_path, "learned") == [0.0, 0.0, 0.0]
    (tmp_path / "psf.json").write_text(json.dumps({"psf": "learned", "intensity_fractions": [0.01, 0.2, 0.3]}))
    assert kernel_of_run(tmp_path, "learned") == [0.01, 0.2, 0.3]
    assert kernel_of_run(tmp_path, "0,0.1,0.1") == [0.0, 0.1, 0.1]
