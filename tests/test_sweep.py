"""Config sweeps: grid parsing, resume after interruption, failures reported, a real sweep."""

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest

from gaussian_atoms_method.harness.sweep import Sweep, SweepError, grid_settings, parse_grid, run_name

BIN = Path(sys.executable).parent


def _data(tmp_path) -> Path:
    data = tmp_path / "data"
    data.mkdir()
    (data / "tilt_series.json").write_text("{}")
    return data


def test_grid_is_every_combination_and_names_are_unique():
    grid = parse_grid(["--pipeline.model.merge-threshold-A 0.2 0.3 0.5", "--pipeline.model.loss l1 l2"])
    settings = grid_settings(grid)
    assert len(settings) == 6
    assert settings[0] == {"--pipeline.model.merge-threshold-A": "0.2", "--pipeline.model.loss": "l1"}
    names = {run_name(s) for s in settings}
    assert len(names) == 6 and all("/" not in n for n in names)
    for bad in (["0.2 0.3"], ["--pipeline.model.loss"], [], ["--a 1", "--a 2"]):
        with pytest.raises(SweepError, match="sweep grid"):
            parse_grid(bad)


def test_sweep_resumes_and_reports_failures(tmp_path):
    calls = []

    def fake_runner(data, run_dir, args, iterations, device, threads):
        calls.append(args)
        if "bad" in args:
            raise RuntimeError("ns-train failed: bad value")
        return {
            "tpr": 1.0,
            "fp_per_true_atom": 0.0,
            "rmsd_pm": float(args[-1]),
            "n_pred": 3,
            "n_true": 3,
            "seconds": 1.0,
        }

    data = _data(tmp_path)
    sweep = Sweep(data, tmp_path / "sweep", grid=("--x 1 2 bad",), jobs=2, runner=fake_runner)
    rows = sweep.run()
    assert [r["status"] for r in rows][:2] == ["ok", "ok"] and rows[2]["status"].startswith("failed: ns-train failed")
    assert len(calls) == 3
    table = list(csv.DictReader(open(tmp_path / "sweep" / "sweep.csv")))
    assert [t["x"] for t in table] == ["1", "2", "bad"] and table[1]["rmsd_pm"] == "2"
    assert "| 2 | 1 | 0 | 2 |" in (tmp_path / "sweep" / "sweep.md").read_text()
    # Interrupted and restarted with one more value: only the failed and the new run go again.
    calls.clear()
    Sweep(data, tmp_path / "sweep", grid=("--x 1 2 bad 3",), runner=fake_runner).run()
    assert sorted(a[-1] for a in calls) == ["3", "bad"]
    # Interrupted mid-sweep (Ctrl-C while the third of four runs trains): the runs that
    # finished before are kept and not repeated.
    calls.clear()

    def interrupted(data, run_dir, args, iterations, device, threads):
        if args[-1] == "6":
            raise KeyboardInterrupt
        return fake_runner(data, run_dir, args, iterations, device, threads)

    with pytest.raises(KeyboardInterrupt):
        Sweep(data, tmp_path / "sweep", grid=("--x 4 5 6 7",), runner=interrupted).run()
    calls.clear()
    Sweep(data, tmp_path / "sweep", grid=("--x 4 5 6 7",), runner=fake_runner).run()
    assert sorted(a[-1] for a in calls) == ["6", "7"]
    # Different shared settings are a different run, not a finished one.
    calls.clear()
    Sweep(data, tmp_path / "sweep", grid=("--x 1",), iterations=10, runner=fake_runner).run()
    assert len(calls) == 1


def test_sweep_errors_name_the_option(tmp_path):
    with pytest.raises(SweepError, match="--data"):
        Sweep(tmp_path / "missing", tmp_path / "out", grid=("--x 1",))
    with pytest.raises(SweepError, match="--jobs"):
        Sweep(_data(tmp_path), tmp_path / "out", grid=("--x 1",), jobs=0)


def test_sweep_on_ray_local_cluster(tmp_path):
    ray = pytest.importorskip("ray")

    def remote_runner(data, run_dir, args, iterations, device, threads):
        import os

        return {"tpr": 1.0, "n_pred": int(args[-1]), "seconds": 0.0, "pid": os.getpid()}

    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        rows = Sweep(
            _data(tmp_path), tmp_path / "sweep", grid=("--x 1 2 3",), backend="ray", runner=remote_runner
        ).run()
    finally:
        ray.shutdown()
    assert [r["n_pred"] for r in rows] == [1, 2, 3]
    assert all(r["pid"] != __import__("os").getpid() for r in rows)  # ran in Ray workers


def test_sweep_cli_trains_each_setting(tmp_path, simulate_sphere):
    """Two real runs side by side on a small Gaussian-potential sphere: each run's config holds
    its own setting (a boolean given as False too), and both are scored against the truth (an
    easy particle: all 55 atoms)."""
    data = tmp_path / "data"
    simulate_sphere(data)
    out = tmp_path / "sweep"
    cmd = [
        str(BIN / "gaussian-atoms"),
        "sweep",
        "--data",
        str(data),
        "--output",
        str(out),
        "--iterations",
        "400",
        "--jobs",
        "2",
        "--",
        "--pipeline.model.merge-threshold-A",
        "0.5",
        "0.7",
        "--pipeline.model.stop-when-converged",
        "False",
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    table = list(csv.DictReader(open(out / "sweep.csv")))
    assert [t["pipeline.model.merge-threshold-A"] for t in table] == ["0.5", "0.7"]
    for row in table:
        assert row["status"] == "ok" and float(row["tpr"]) == 1.0 and float(row["fp_per_true_atom"]) == 0.0
        config = (out / "runs" / row["run"] / "ours" / "gaussian-atoms" / "run" / "config.yml").read_text()
        assert f"merge_threshold_A: {row['pipeline.model.merge-threshold-A']}" in config
        assert "stop_when_converged: false" in config  # a boolean grid value, as ns-train takes it
        assert json.loads((out / "runs" / row["run"] / "result.json").read_text())["settings"]
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0 and "2 already finished, 0 to run" in again.stdout
