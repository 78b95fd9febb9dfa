"""Reading and validating tilt-series directories: good input round-trips, bad input is named."""

import json

import numpy as np
import pytest

from dataparsers.tilt_series_format import TiltSeriesError, load_tilt_series, write_tilt_series
from gaussian_atoms_method.atoms.atom_set import AtomSet


def _write(tmp_path, n=5, shape=(8, 9)):
    rng = np.random.default_rng(0)
    proj = rng.normal(size=(n,) + shape).astype(np.float32)  # negative values must survive
    angles = np.linspace(-60, 60, n)
    truth = AtomSet(np.array([[1.0, 2.0, 3.0]]), species=["Au"])
    write_tilt_series(tmp_path, proj, angles, 0.25, truth=truth, origin_A=(1.0, 2.0, 3.0))
    return proj, angles


def test_round_trip_keeps_floats_unquantised(tmp_path):
    proj, angles = _write(tmp_path)
    series = load_tilt_series(tmp_path)
    np.testing.assert_array_equal(series.projections, proj)
    np.testing.assert_allclose(series.angles_deg, angles, atol=1e-6)
    assert series.pixel_size_A == 0.25 and series.tilt_axis == "y"
    assert series.projections.min() < 0
    np.testing.assert_array_equal(series.origin_A, [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(series.centre_px, [3.5, 4.0])
    assert series.truth_path == tmp_path / "atoms_true.xyz"


def test_a_replica_keeps_the_noise_drawn_into_its_views(tmp_path):
    rng = np.random.default_rng(1)
    noise = rng.normal(size=(5, 8, 9)).astype(np.float32)
    write_tilt_series(tmp_path, 10 + noise, np.linspace(-60, 60, 5), 0.25, noise=noise)
    series = load_tilt_series(tmp_path)
    assert series.noise_path == tmp_path / "noise.npy"
    np.testing.assert_array_equal(np.load(series.noise_path), noise)
    _write(tmp_path / "measured")
    assert load_tilt_series(tmp_path / "measured").noise_path is None


def test_options_override_manifest(tmp_path):
    _write(tmp_path)
    series = load_tilt_series(tmp_path, pixel_size_A=0.5, tilt_axis="x")
    assert series.pixel_size_A == 0.5 and series.tilt_axis == "x"


def test_options_without_manifest(tmp_path):
    np.save(
        tmp_path / "p.npy", np.random.default_rng(0).uniform(1, 2, (3, 5, 5))
    )  # the smallest image the noise reading takes
    np.savetxt(tmp_path / "a.txt", [-10.0, 0.0, 10.0])
    series = load_tilt_series(tmp_path, projections="p.npy", angles_deg="a.txt", pixel_size_A=0.3)
    assert series.n_views == 3


def _edit_manifest(tmp_path, **changes):
    m = json.loads((tmp_path / "tilt_series.json").read_text())
    m.update(changes)
    (tmp_path / "tilt_series.json").write_text(json.dumps(m))


@pytest.mark.parametrize(
    "break_it, file_name, words",
    [
        (lambda d: np.savetxt(d / "angles.txt", np.arange(4.0)), "angles.txt", "4 tilt angles for 5 projections"),
        (
            lambda d: np.save(d / "projections.npy", np.full((5, 8, 9), np.nan, np.float32)),
            "projections.npy",
            "NaN/Inf",
        ),
        (lambda d: np.save(d / "projections.npy", np.ones((5, 8), np.float32)), "projections.npy", "3D stack"),
        (lambda d: _edit_manifest(d, pixel_size_A=0), "tilt_series.json", "positive"),
        (lambda d: _edit_manifest(d, pixel_size_A=-0.1), "tilt_series.json", "positive"),
        (lambda d: (d / "projections.npy").unlink(), "projections.npy", "not found"),
        (lambda d: np.savetxt(d / "angles.txt", [0.0, 10.0, 10.0, 20.0, 30.0]), "angles.txt", "duplicate tilt angle"),
        (lambda d: _edit_manifest(d, tilt_axis="z"), "tilt_series.json", "tilt_axis"),
        (lambda d: _edit_manifest(d, truth="missing.xyz"), "missing.xyz", "not found"),
        (lambda d: _edit_manifest(d, noise="missing.npy"), "missing.npy", "not found"),
        (lambda d: _edit_manifest(d, colour="red"), "tilt_series.json", "unknown key"),
        (lambda d: (d / "tilt_series.json").write_text("{not json"), "tilt_series.json", "not valid JSON"),
    ],
)
def test_bad_input_names_file_and_problem(tmp_path, break_it, file_name, words):
    _write(tmp_path)
    break_it(tmp_path)
    with pytest.raises(TiltSeriesError) as info:
        load_tilt_series(tmp_path)
    message = str(info.value)
    assert "\n" not in message
    assert file_name in message and words in message, message


def test_missing_directory(tmp_path):
    with pytest.raises(TiltSeriesError, match="not found"):
        load_tilt_series(tmp_path / "nowhere")


def test_manifest_written_last(tmp_path):
    """A directory with a manifest is complete: writing fails before the manifest appears."""
    with pytest.raises(TiltSeriesError):
        write_tilt_series(tmp_path, np.ones((2, 3, 3)), [0.0, 0.0], 0.25)
    assert not (tmp_path / "tilt_series.json").exists()


def _series_with_bad_view(tmp_path, bad):
    """A valid 7-view series (-60..60 deg) whose view 2 (-20 deg) is ``bad``: NaN or a blank."""
    from gaussian_atoms_method.harness.input_cases import valid_series

    data = valid_series(tmp_path / "series")
    p = np.load(data / "projections.npy")
    p[2] = bad
    np.save(data / "projections.npy", p)
    return data


@pytest.mark.parametrize("bad, words", [(np.nan, "NaN/Inf value(s), in view(s) 2 (-20°)"), (0.0, "view(s) 2 (-20°)")])
def test_a_view_that_cannot_be_fitted_is_named_and_can_be_left_out(tmp_path, bad, words):
    """A view holding NaN, or one value everywhere (a blank frame), is refused by its index in
    the file and its tilt, with the option that leaves it out; left out by index or by tilt,
    the series loads without it and keeps each view's index in the file."""
    data = _series_with_bad_view(tmp_path, bad)
    with pytest.raises(TiltSeriesError) as info:
        load_tilt_series(data)
    assert words in str(info.value) and "--drop-views 2" in str(info.value), str(info.value)
    for spec in ("2", "-20deg", [2]):
        series = load_tilt_series(data, drop_views=spec)
        assert series.n_views == 6 and series.view_indices.tolist() == [0, 1, 3, 4, 5, 6]
        np.testing.assert_allclose(series.angles_deg, [-60, -40, 0, 20, 40, 60])
    _edit_manifest(data, drop_views="2")
    assert load_tilt_series(data).n_views == 6


@pytest.mark.parametrize(
    "spec, words",
    [("9", "view 9 is not among the 7 views"), ("-25deg", "no view at -25°"), ("x", "expected view indices")],
)
def test_views_to_leave_out_that_name_no_view_are_refused(tmp_path, spec, words):
    from gaussian_atoms_method.harness.input_cases import valid_series

    with pytest.raises(TiltSeriesError, match=words):
        load_tilt_series(valid_series(tmp_path / "series"), drop_views=spec)


def test_the_series_says_where_its_pixel_size_came_from(tmp_path):
    from gaussian_atoms_method.harness.input_cases import valid_series

    data = valid_series(tmp_path / "series")
    assert load_tilt_series(data).pixel_size_source.endswith("tilt_series.json")
    assert load_tilt_series(data, pixel_size_A=0.25).pixel_size_source == "the pixel_size_A option"


def _particle_views():
    """A small Au particle's views (Gaussian potential, noise 20): atoms bright."""
    from gaussian_atoms_method.harness.simulate import simulate_gaussian_tilt_series, spherical_particle

    angles = np.linspace(-60, 60, 9)
    sim = simulate_gaussian_tilt_series(spherical_particle("Au", 7.0), angles, noise_std=20.0, seed=1)
    return sim.projections, angles


def test_dark_atoms_are_named_before_a_fit():
    from dataparsers.tilt_series_format import TiltSeries

    """Views whose atoms are dark on a bright background (bright-field, or a stack saved
    inverted) are refused in one line that says so; the same views with atoms bright load."""
    views, angles = _particle_views()
    assert TiltSeries(views, angles, 0.25).n_views == 9
    for dark in (-views, views.max() - views):
        with pytest.raises(TiltSeriesError, match="atoms look dark on a brighter background") as info:
            TiltSeries(dark, angles, 0.25)
        assert "\n" not in str(info.value)


@pytest.mark.parametrize("factor, words", [(4.0, "times too large"), (0.25, "times too small")])
def test_a_pixel_size_that_puts_atoms_at_impossible_widths_is_refused(factor, words):
    """A Au particle at 0.25 Å pixels (its images read 0.37 Å wide): said to be four times as
    large the images would be 1.5 Å wide (no probe that separates atoms is that broad), a quarter
    0.09 Å (under the potential's own core); each is refused in one line with the factor it is
    off by (against the 0.35 Å the measure reads on every series: 4.3 here), the true size loads."""
    from dataparsers.tilt_series_format import TiltSeries
    from dataparsers.views import atom_image_sigma_px

    views, angles = _particle_views()
    assert TiltSeries(views, angles, 0.25).n_views == 9
    assert 0.3 < atom_image_sigma_px(views) * 0.25 < 0.4
    with pytest.raises(TiltSeriesError, match=words) as info:
        TiltSeries(views, angles, 0.25 * factor)
    off = float(str(info.value).split("about ")[-1].split(" times")[0])
    assert "\n" not in str(info.value) and 3.5 < off < 4.5


def test_noise_alone_tells_no_atom_width():
    """Views of white noise hold no structure to read a width from: nothing is refused."""
    from dataparsers.views import atom_image_sigma_px

    assert np.isnan(atom_image_sigma_px(np.random.default_rng(0).normal(0, 1, (9, 80, 80))))
