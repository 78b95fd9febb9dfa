"""The start begun in a thread while the launcher loads: the model gets the same start as its own,
only where the inputs are the same; the command line's scan; both launchers use it on a CPU."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from dataparsers.tilt_series_format import load_tilt_series, write_tilt_series
from gaussian_atoms_method.atoms.initialise import compute_start
from gaussian_atoms_method.harness.input_cases import own_lines, valid_series
from gaussian_atoms_method.harness.simulate import simulate_tilt_series, spherical_particle
from gaussian_atoms_method.launch import start_ahead
from gaussian_atoms_method.physics.noise import measure_noise
from gaussian_atoms_method.physics.units import normalised_projections

BIN = Path(sys.executable).parent


@pytest.fixture(scope="module")
def series_dir(tmp_path_factory) -> Path:
    """A 43-atom Au sphere, 15 tilts, the model's own physics: a start with candidates."""
    truth = spherical_particle("Au", radius_A=5.0)
    sim = simulate_tilt_series(truth, np.arange(-70.0, 71.0, 10.0), potential="gaussian", noise_std=20.0, seed=0)
    return write_tilt_series(
        tmp_path_factory.mktemp("ahead") / "series", sim.projections, sim.angles_deg, sim.pixel_size_A, truth=truth
    )


def _inputs(data: Path):
    series = load_tilt_series(data)
    normalisation, scaled = normalised_projections(series)
    return series, torch.from_numpy(scaled), normalisation


def test_the_start_begun_ahead_is_the_one_computed_in_line(series_dir):
    """On a GPU the thread makes the noise reading and back-projection there first
    (start_ahead.start_parts), on this CPU in numpy before torch: the same start either way.  The
    interpreter's switch interval is its own again once the thread is done."""
    series, projections, normalisation = _inputs(series_dir)
    interval = sys.getswitchinterval()
    start_ahead.begin(series_dir)
    ahead = start_ahead.take(series, projections, normalisation, "auto", 1.5)
    assert sys.getswitchinterval() == interval
    in_line = compute_start(series, projections, normalisation, "auto", 1.5, noise=measure_noise(projections))
    assert ahead is not None and len(in_line.means) > 0
    # The same functions on the same data: the same bits, whichever thread ran them.
    assert torch.equal(ahead.means, in_line.means) and torch.equal(ahead.weights, in_line.weights)
    assert ahead.noise == in_line.noise and ahead.field == in_line.field
    assert start_ahead.take(series, projections, normalisation, "auto", 1.5) is None  # handed out once


def test_the_noise_measured_ahead_is_the_taken_starts_own(series_dir, tmp_path):
    """The run reads the noise beside the candidates from the noise the thread measured
    (start_ahead.measured_noise): for the same file, the very noise the start it then takes
    holds, without handing the start out; for another file, none."""
    series, projections, normalisation = _inputs(series_dir)
    start_ahead.begin(series_dir)
    other = write_tilt_series(tmp_path / "other", np.load(series_dir / "projections.npy"), series.angles_deg, 0.25)
    assert start_ahead.measured_noise(load_tilt_series(other)) is None
    noise = start_ahead.measured_noise(series)
    assert noise is not None and noise == measure_noise(projections)  # the run's own reading
    assert start_ahead.take(series, projections, normalisation, "auto", 1.5).noise is noise


@pytest.mark.parametrize("change", ["option", "width", "normalisation", "pixel size", "projections"])
def test_a_start_for_other_inputs_is_not_taken(series_dir, change):
    series, projections, normalisation = _inputs(series_dir)
    option, width = "auto", 1.5
    start_ahead.begin(series_dir)
    if change == "option":
        option = "on"
    elif change == "width":
        width = 1.2
    elif change == "normalisation":
        normalisation = type(normalisation)(normalisation.length_scale * 2, normalisation.data_scale)
    elif change == "pixel size":
        series.pixel_size_A *= 1.01
    else:
        projections = projections.clone()
        projections[0, 0, 0] += 1.0
    assert start_ahead.take(series, projections, normalisation, option, width) is None


def test_a_start_for_another_file_is_not_waited_for(series_dir, tmp_path):
    other = write_tilt_series(
        tmp_path / "other", np.load(series_dir / "projections.npy"), load_tilt_series(series_dir).angles_deg, 0.25
    )
    series, projections, normalisation = _inputs(other)
    start_ahead.begin(series_dir)
    assert start_ahead.take(series, projections, normalisation, "auto", 1.5) is None


def test_an_unreadable_series_leaves_the_run_to_report_it(tmp_path):
    start_ahead.begin(tmp_path / "missing")
    ahead = start_ahead._ahead
    ahead.thread.join(timeout=60)
    assert ahead.read.is_set() and ahead.series is None and ahead.start is None
    series, projections, normalisation = _inputs(valid_series(tmp_path / "valid"))
    assert start_ahead.take(series, projections, normalisation, "auto", 1.5) is None


@pytest.mark.parametrize(
    "argv, expected",
    [
        (["--vis", "tensorboard", "tilt-series", "--data", "d"], {"data": Path("d")}),
        (["--data", "d", "--max-num-iterations", "2"], {"data": Path("d")}),
        (
            [
                "--pipeline.model.extended_object",
                "on",
                "--pipeline.model.max-atom-sigma-a=2",
                "tilt-series",
                "--data=d",
            ],
            {"data": Path("d"), "extended_object": "on", "max_atom_sigma_A": 2.0},
        ),
        (["tilt-series", "--data", "d", "--pixel-size-A", "0.3"], None),  # the series read with options of its own
        (["--help", "tilt-series", "--data", "d"], None),
        (["--pipeline.model.init", "random", "tilt-series", "--data", "d"], None),
        (["--pipeline.model.start-atoms", "a.xyz", "tilt-series", "--data", "d"], None),
        (["--load-config", "c.yml"], None),
        (["tilt-series"], None),
        (["--pipeline.model.max-atom-sigma-A", "wide", "--data", "d"], None),
    ],
)
def test_the_command_line_names_the_start(argv, expected):
    assert start_ahead.requested_start(argv) == expected


def test_begun_for_a_command_line_that_names_the_series(monkeypatch):
    """Begun on every device (on a GPU the start runs there, in the thread); not where the
    command line names no series."""
    begun = []
    monkeypatch.setattr(start_ahead, "begin", lambda **kw: begun.append(kw))
    assert start_ahead.begin_for(["tilt-series", "--data", "d"]) and begun == [{"data": Path("d"), "on_gpu": True}]
    assert not start_ahead.begin_for(["tilt-series"]) and len(begun) == 1
    assert start_ahead.begin_for(["--machine.device-type", "cpu", "tilt-series", "--data", "d"])
    assert begun[-1] == {"data": Path("d"), "on_gpu": False}  # a CPU run's start stays on the host


@pytest.mark.parametrize("launcher", [["ns-train", "gaussian-atoms"], ["gaussian-atoms", "train"]])
def test_both_launchers_start_ahead(launcher, series_dir, tmp_path):
    cmd = [
        str(BIN / launcher[0]),
        *launcher[1:],
        "--max-num-iterations",
        "2",
        "--machine.device-type",
        "cpu",
        "--vis",
        "tensorboard",
        "--output-dir",
        str(tmp_path),
        "tilt-series",
        "--data",
        str(series_dir),
    ]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "start at back-projection maxima (found while the launcher loaded)" in run.stdout


def test_a_run_stopped_by_a_bad_option_while_the_start_runs_ends_in_one_line(series_dir, tmp_path):
    cmd = [
        str(BIN / "gaussian-atoms"),
        "train",
        "--pipeline.model.min-sigma-A",
        "-1",
        "--machine.device-type",
        "cpu",
        "--vis",
        "tensorboard",
        "--output-dir",
        str(tmp_path / "out"),
        "tilt-series",
        "--data",
        str(series_dir),
    ]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert run.returncode == 2 and own_lines(run.stdout + run.stderr) == [
        "gaussian-atoms: error: --pipeline.model.min-sigma-A must be positive, got -1.0"
    ]
    assert "terminate called" not in run.stderr and not (tmp_path / "out").exists()


def test_the_start_ahead_begins_before_torch_is_imported():
    """The launcher imports this module and begins the start before it imports torch: the
    module, and the noise reading the thread makes first, import no torch."""
    code = (
        "import sys, numpy as np\n"
        "from gaussian_atoms_method.launch import start_ahead\n"
        "from gaussian_atoms_method.physics.noise import HOST, measure_noise\n"
        "from gaussian_atoms_method.physics.reconstruction import backprojection_for_peaks\n"
        "p = np.random.default_rng(0).normal(5.0, 1.0, (5, 33, 33))\n"
        "assert measure_noise(p, device=HOST).read_var > 0\n"
        "v = backprojection_for_peaks(p, np.linspace(-60, 60, 5), 0.5, device=HOST)\n"
        "assert isinstance(v.data, np.ndarray) and v.data.dtype == np.float32\n"
        "assert 'torch' not in sys.modules, 'torch imported'\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr[-2000:]


def test_where_a_gpu_may_be_seen_the_thread_leaves_the_host_work_to_the_start(series_dir, monkeypatch):
    """Where a GPU's device files exist the thread reads no noise and makes no back-projection
    before torch is imported (the run makes them on the GPU); the start it computes is still the
    one computed in line, to the bit."""
    monkeypatch.setattr(start_ahead, "gpu_possible", lambda: True)
    series, projections, normalisation = _inputs(series_dir)
    start_ahead.begin(series_dir)
    ahead = start_ahead.take(series, projections, normalisation, "auto", 1.5)
    in_line = compute_start(series, projections, normalisation, "auto", 1.5, noise=measure_noise(projections))
    assert ahead is not None and torch.equal(ahead.means, in_line.means) and torch.equal(ahead.weights, in_line.weights)
    assert ahead.noise == in_line.noise


def test_the_thread_imports_scipys_packages_before_the_launcher_imports_them(series_dir):
    """scipy's packages import one another in cycles: the start's thread imports them first (while
    the launcher imports torch) and the launcher waits for that (settle_imports) before its own
    imports of them, so the two threads never import them at once."""
    code = (
        "import sys\n"
        "from gaussian_atoms_method.launch import start_ahead\n"
        "assert not any(m in sys.modules for m in start_ahead.SHARED_IMPORTS), 'imported before the thread'\n"
        f"start_ahead.begin({str(series_dir)!r})\n"
        "start_ahead.settle_imports()\n"
        "missing = [m for m in start_ahead.SHARED_IMPORTS if m not in sys.modules]\n"
        "assert not missing, missing\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr[-2000:]


def test_a_run_asked_for_the_cpu_starts_on_the_host_where_a_gpu_is_seen(series_dir, monkeypatch):
    """``--machine.device-type cpu`` on a machine with a GPU: the thread's noise, back-projection
    and candidates stay on the CPU (this torch has no CUDA, so any GPU work would fail and leave
    no start), and the start is the one computed in line, to the bit."""
    series, projections, normalisation = _inputs(series_dir)
    in_line = compute_start(series, projections, normalisation, "auto", 1.5, noise=measure_noise(projections))
    monkeypatch.setattr(start_ahead, "gpu_possible", lambda: True)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert start_ahead.begin_for(["--machine.device-type", "cpu", "tilt-series", "--data", str(series_dir)])
    ahead = start_ahead.take(series, projections, normalisation, "auto", 1.5)
    assert ahead is not None and torch.equal(ahead.means, in_line.means) and torch.equal(ahead.weights, in_line.weights)
