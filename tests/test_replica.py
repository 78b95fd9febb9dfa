"""A replica of a user's own series (harness/replica.py, ``simulate --like``): its geometry, level
and noise are the real series', its truth the atoms given."""

import contextlib
import io
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dataparsers.tilt_series_format import TiltSeries, load_tilt_series, write_tilt_series
from gaussian_atoms_method.atoms.atom_set import AtomSet, read_atoms
from gaussian_atoms_method.harness.replica import replica_of
from gaussian_atoms_method.physics.noise import noise_from_projections

GRID_A = np.stack(np.meshgrid([-2.7, 0.0, 2.7], [-1.35, 1.35], [-1.35, 1.35], indexing="ij"), -1).reshape(-1, 3)
"""12 places 2.7 Å apart: Ta atoms near them keep clear of tantalum's shortest bond (2.11 Å)."""


def _real_like(tmp_path: Path, atoms: AtomSet | None = None) -> Path:
    """A 'real' series of Euler views (RESIRE's convention), off-centre tilt centre, Poisson-like
    noise (variance 4 + 0.5 x level), with a truth file: 12 Ta atoms on a 2.7 Å grid moved by up
    to 0.2 Å (a specimen that can exist: no two closer than tantalum's shortest bond, 2.11 Å), or
    ``atoms``."""
    rng = np.random.default_rng(0)
    if atoms is None:
        atoms = AtomSet(GRID_A + rng.uniform(-0.2, 0.2, GRID_A.shape), species=["Ta"] * 12)
    euler = np.c_[np.full(15, 0.2), np.linspace(-60, 55, 15), np.full(15, -0.3)]
    geometry = TiltSeries(
        np.broadcast_to(np.linspace(1.0, 2.0, 40), (15, 48, 40)),  # a ramp: views that hold no noise
        euler,
        0.3,
        centre_px=(24.0, 19.0),
        euler_convention="zyx",
    )
    clean = replica_of(geometry, atoms, probe="none", potential="gaussian").projections.astype(np.float64)
    clean = 200.0 * clean / clean.mean() + 50.0
    noisy = clean + rng.standard_normal(clean.shape) * np.sqrt(4.0 + 0.5 * clean)
    return write_tilt_series(
        tmp_path / "real", noisy, euler, 0.3, truth=atoms, centre_px=(24.0, 19.0), euler_convention="zyx"
    )


def _simulate_like(real_dir: Path, output: Path, *options: str) -> None:
    """``gaussian-atoms simulate --like REAL_DIR --output OUTPUT OPTIONS``, which must succeed."""
    result = subprocess.run(
        [str(Path(sys.executable).parent / "gaussian-atoms"), "simulate", "--like", str(real_dir)]
        + ["--output", str(output), *options],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, result.stderr[-2000:]


def test_a_replica_takes_the_series_geometry_level_and_noise(tmp_path):
    """``simulate --like``: the same views (orientations and their convention, detector, pixel,
    tilt centre), the truth the real series' atoms, the mean level the real one's, and the noise
    read from the replica what was read from the real views (the reading's own scatter at these
    sizes is a few percent of the gain)."""
    real_dir = _real_like(tmp_path)
    _simulate_like(real_dir, tmp_path / "replica", "--probe", "aberrated", "--shift-px", "0.3", "--support-A", "10")
    real, replica = load_tilt_series(real_dir), load_tilt_series(tmp_path / "replica")
    assert replica.projections.shape == real.projections.shape
    assert replica.euler_convention == "zyx" and replica.pixel_size_A == real.pixel_size_A
    np.testing.assert_allclose(replica.euler_deg, real.euler_deg, atol=1e-6)
    np.testing.assert_allclose(replica.centre_px, real.centre_px)
    np.testing.assert_allclose(
        read_atoms(replica.truth_path).positions, read_atoms(real.truth_path).positions, atol=1e-6
    )
    assert replica.projections.mean() == pytest.approx(real.projections.mean(), rel=0.02)
    ours, theirs = noise_from_projections(replica.projections), noise_from_projections(real.projections)
    assert ours.gain == pytest.approx(theirs.gain, rel=0.15)


def test_a_replica_cropped_by_interpolation_holds_correlated_noise_the_run_reads_within_20_percent(tmp_path):
    """``simulate --like --crop-order 3``: each noisy view cropped about a random sub-pixel
    centre with cubic splines, as measured views are (its atoms drawn where the crop brings
    them back to).  Its noise
    is correlated: neighbouring pixels read about half the variance drawn, the run's reading
    (the spectrum beyond the atoms, :mod:`~gaussian_atoms_method.physics.noise_spectrum`) within 20%
    of it (0.98 here)."""
    from gaussian_atoms_method.physics.noise import measure_noise

    real_dir = _real_like(tmp_path)
    result = subprocess.run(
        [str(Path(sys.executable).parent / "gaussian-atoms"), "simulate", "--like", str(real_dir)]
        + ["--output", str(tmp_path / "replica"), "--crop-order", "3", "--seed", "1"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    views = load_tilt_series(tmp_path / "replica").projections.astype(np.float64)
    level = np.array([views.mean()])
    drawn = noise_from_projections(load_tilt_series(real_dir).projections).variance(level)[0]
    assert noise_from_projections(views).variance(level)[0] < 0.7 * drawn
    noise = measure_noise(views)
    assert noise.correlation > 1.2 and noise.variance(level)[0] == pytest.approx(drawn, rel=0.2)


def test_a_replica_drawn_with_the_noise_a_run_read_over_an_atom_is_read_again_within_20_percent(tmp_path):
    """``simulate --like --noise-over-atom 50 --noise-sigma-A 0.55``: the noise of denoised views
    (a 0.7 px blur here), its pixels at the real views' variance and an atom seeing 50 times it.  The
    replica keeps the noise it drew (``noise.npy``); a run on it reads the noise from what
    neighbouring views do not share, checks that against the noise drawn, read the same way in its
    own units, and finds it within 20% (15 views of 48 x 40 px leave the filtered views few
    independent samples: 0.89 and 0.91 with seeds 1 and 2), and says how to draw it again."""
    import re

    import gaussian_atoms_method as ga

    real_dir = _real_like(tmp_path)
    _simulate_like(real_dir, tmp_path / "replica", "--noise-over-atom", "50", "--noise-sigma-A", "0.55", "--seed", "1")
    replica = load_tilt_series(tmp_path / "replica")
    assert replica.noise_path == tmp_path / "replica" / "noise.npy"
    level = np.array([replica.projections.mean()])
    drawn = noise_from_projections(load_tilt_series(real_dir).projections).variance(level)[0]
    assert noise_from_projections(replica.projections).variance(level)[0] == pytest.approx(drawn, rel=0.2)
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        ga.reconstruct(replica, device="cpu", species="Ta", progress=False)
    said = re.sub(r"\s+", " ", out.getvalue())  # the console wraps its lines
    read = re.search(
        r"residual: ([0-9.e+]+) times the variance neighbouring pixels show \(.*?atoms ([0-9.]+) Å wide", said
    )
    checked = re.search(r"noise over an atom read ([0-9.e+]+) times .*? holds ([0-9.e+]+) times it there", said)
    assert float(checked[1]) == pytest.approx(float(read[1]), rel=0.01)
    assert float(checked[1]) == pytest.approx(float(checked[2]), rel=0.2)
    assert f"--noise-over-atom {read[1]} --noise-sigma-A {read[2]}" in said


def test_the_replica_names_what_it_cannot_use(tmp_path):
    """A series without a truth file and no atoms given: one line naming the option."""
    series = TiltSeries(np.random.default_rng(1).uniform(1, 2, (5, 20, 20)), np.linspace(-40, 40, 5), 0.3)
    data = write_tilt_series(tmp_path / "s", series.projections, series.angles_deg, 0.3)
    result = subprocess.run(
        [str(Path(sys.executable).parent / "gaussian-atoms"), "simulate", "--like", str(data)]
        + ["--output", str(tmp_path / "r")],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode != 0 and "Traceback" not in result.stderr
    assert "give the atoms as --particle FILE" in result.stderr
    assert not (tmp_path / "r").exists()


def test_a_replica_takes_each_views_shift_when_given(tmp_path):
    """``replica_of(..., shifts_px=)``: the misregistration a registration run read on the real
    views, instead of random shifts.  Against the replica of the same seed without them each
    view's content sits at its shift (``best_registration``, to 0.05 px; 0.014 read: the two
    replicas share their noise's draws but not its place)."""
    from gaussian_atoms_method.atoms.view_prediction import best_registration

    series = load_tilt_series(_real_like(tmp_path))
    atoms = read_atoms(series.truth_path)
    shifts = np.c_[np.linspace(-1.0, 1.0, 15), np.linspace(0.5, -0.5, 15)]
    shifted = replica_of(series, atoms, probe="gaussian", seed=3, shifts_px=shifts)
    plain = replica_of(series, atoms, probe="gaussian", seed=3)
    np.testing.assert_array_equal(shifted.shifts_px, shifts)
    found = np.array([best_registration(a, b)[0] for a, b in zip(shifted.projections, plain.projections)])
    np.testing.assert_allclose(found, shifts, atol=0.05)


def test_simulate_takes_the_shifts_a_registration_file_holds(tmp_path):
    """``simulate --like DIR --shifts-from registration.csv`` (the file a fit that learns shifts
    writes): the replica is the one :func:`replica_of` makes with those shifts (the same draws:
    equal to float32 rounding).  A file of another series' views, or beside ``--shift-px``, is
    named in one line before anything is written."""
    from dataparsers.registration_file import read_registration, write_registration

    real_dir = _real_like(tmp_path)
    series = load_tilt_series(real_dir)
    shifts = np.c_[np.linspace(-1.0, 1.0, 15), np.linspace(0.5, -0.5, 15)]
    write_registration(tmp_path / "registration.csv", shifts, np.ones(15))
    write_registration(tmp_path / "other.csv", shifts[:14], np.ones(14))
    command = [str(Path(sys.executable).parent / "gaussian-atoms"), "simulate", "--like", str(real_dir)]

    def simulate(*options: str) -> subprocess.CompletedProcess:
        return subprocess.run(command + list(options), capture_output=True, text=True, timeout=600)

    result = simulate("--output", str(tmp_path / "r"), "--shifts-from", str(tmp_path / "registration.csv"))
    assert result.returncode == 0, result.stderr[-2000:]
    written = read_registration(tmp_path / "registration.csv")[0]  # six digits: 0.0714286 px
    np.testing.assert_allclose(written, shifts, atol=1e-6)
    # simulate --like's defaults are replica_of's: Lobato ADF atoms through the default optics
    expected = replica_of(series, read_atoms(series.truth_path).shifted(-np.asarray(series.origin_A)),
                          seed=0, shifts_px=written)  # fmt: skip
    np.testing.assert_allclose(load_tilt_series(tmp_path / "r").projections, expected.projections, rtol=1e-6)
    for options, fragment in (
        (["--shifts-from", str(tmp_path / "other.csv")], "14 views' shifts"),
        (["--shifts-from", str(tmp_path / "registration.csv"), "--shift-px", "0.5"], "give one"),
        (["--shifts-from", str(tmp_path / "missing.csv")], "missing.csv: cannot read it"),
    ):
        result = simulate("--output", str(tmp_path / "bad"), *options)
        assert result.returncode != 0 and "Traceback" not in result.stderr and fragment in result.stderr
        assert len(result.stderr.strip().splitlines()) == 1 and not (tmp_path / "bad").exists()


def test_a_replicas_truth_holds_no_pair_physics_forbids(tmp_path):
    """A measured model may hold pairs closer than any bond of its elements (the Ta film's: down
    to 1.53 Å, where tantalum's shortest possible bond is 2.11 Å); no specimen holds them, so
    ``simulate --like`` sets one of each aside (the most atoms with no such pair: of a chain of
    three, its ends) and says so in a line; ``--keep-close-pairs`` keeps the atoms as given."""
    from gaussian_atoms_method.atoms.hard_core import close_pairs, shortest_bond_from_species

    bond = shortest_bond_from_species("Ta")
    chain = np.array([[-1.3, 0.0, 0.0], [0.1, 0.0, 0.0], [1.5, 0.0, 0.0]])  # 1.4 Å apart, 2.8 Å end to end
    atoms = AtomSet(np.r_[GRID_A[[0, 1, 10, 11]], chain], species=["Ta"] * 7)  # 2.26 Å and more from the chain
    assert len(close_pairs(atoms.positions, bond)) == 2
    real_dir = _real_like(tmp_path, atoms)
    command = [str(Path(sys.executable).parent / "gaussian-atoms"), "simulate", "--like", str(real_dir)]
    for options, kept in (([], 6), (["--keep-close-pairs"], 7)):
        out = tmp_path / f"r{len(options)}"
        result = subprocess.run(command + ["--output", str(out), *options], capture_output=True, text=True, timeout=600)
        assert result.returncode == 0, result.stderr[-2000:]
        truth = read_atoms(load_tilt_series(out).truth_path).positions
        assert len(truth) == kept
        said = "1 of the 7 atoms lie closer to another than the shortest bond their elements can form (2.11 Å"
        assert (said in result.stdout) == (kept == 6)
    assert len(close_pairs(truth, bond)) == 2  # kept as given
    truth = read_atoms(load_tilt_series(tmp_path / "r0").truth_path).positions
    assert len(close_pairs(truth, bond)) == 0 and not np.any(np.all(np.isclose(truth, chain[1]), axis=1))


def test_a_correlated_noise_without_the_width_it_was_read_at_is_refused_before_any_drawing(tmp_path):
    """A factor over an atom means nothing without the atom's width: one line naming both options,
    a non-zero exit, no output directory."""
    real_dir = _real_like(tmp_path)
    result = subprocess.run(
        [str(Path(sys.executable).parent / "gaussian-atoms"), "simulate", "--like", str(real_dir)]
        + ["--output", str(tmp_path / "r"), "--noise-over-atom", "50"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode != 0 and "Traceback" not in result.stderr
    assert "--noise-over-atom 50" in result.stderr and "--noise-sigma-A" in result.stderr
    assert not (tmp_path / "r").exists()
