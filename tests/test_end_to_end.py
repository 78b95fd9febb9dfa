"""The whole chain from a clean install: simulate -> ns-train gaussian-atoms (CPU) -> atoms -> evaluate."""

import json
import os
import stat
import subprocess
import sys
from pathlib import Path

import ase.io
import numpy as np
import pytest

BIN = Path(sys.executable).parent


def _run(*args, **kw):
    return subprocess.run([str(a) for a in args], capture_output=True, text=True, timeout=600, **kw)


def test_ns_train_lists_method_and_dataparser():
    top = _run(BIN / "ns-train", "--help")
    assert top.returncode == 0 and "gaussian-atoms" in top.stdout
    method = _run(BIN / "ns-train", "gaussian-atoms", "--help")
    assert method.returncode == 0 and "tilt-series" in method.stdout
    assert "Warning" not in method.stderr, method.stderr  # hidden by the start-up hook the install places


def test_simulate_train_evaluate(tmp_path, simulate_sphere):
    data = tmp_path / "data"
    simulate_sphere(data, 6, "-70:5:70")
    train = _run(
        BIN / "ns-train",
        "gaussian-atoms",
        "--machine.device-type",
        "cpu",
        "--vis",
        "tensorboard",
        "--output-dir",
        tmp_path / "out",
        "--experiment-name",
        "e2e",
        "--timestamp",
        "run",
        # the default budget: the run stops where it converges (1,100 steps here); with 1,000 the
        # last residual search, and the split of a Gaussian heavier than a single atom it
        # proposes, fall at step 700 and the set has 300 steps to settle
        "--max-num-iterations",
        "3000",
        "--pipeline.model.num-random",
        "1500",
        "tilt-series",
        "--data",
        data,
        preexec_fn=lambda: os.umask(0o022),
    )
    assert train.returncode == 0, train.stdout[-3000:] + train.stderr[-3000:]
    # The data's noise is additive Gaussian (noise-std 20): the residuals' variance-mean
    # relation says so (physics/noise.py; tests/test_noise.py for Poisson and mixed noise).
    assert "residual noise is additive" in " ".join(train.stdout.split())
    run = tmp_path / "out" / "e2e" / "gaussian-atoms" / "run"
    atoms = ase.io.read(run / "atoms.xyz")
    truth = ase.io.read(data / "atoms_true.xyz")
    assert (run / "atoms.csv").is_file() and (run / "config.yml").is_file() and (run / "slices.png").is_file()
    # Under umask 022 a colleague on the same machine can read every result (not mkstemp's 0600).
    for name in (
        "atoms.xyz",
        "atoms.csv",
        "non_atoms.xyz",
        "slices.png",
        "classes.png",
        "rdf.png",
        "structure.json",
        "evaluation.json",
    ):
        assert stat.S_IMODE(os.stat(run / name).st_mode) & 0o044 == 0o044, name
    # Each atom's position precision (Cramér-Rao, tests/test_uncertainty.py): at a peak-to-noise
    # near 70 and 29 views, about a pm per axis, never above the 5 pm the RMSD is held to below.
    std = atoms.arrays["position_std_A"]
    assert std.shape == (len(atoms), 3) and np.all((std > 1e-3) & (std < 0.05))
    # Each atom's evidence (atoms/evidence.py): at that peak-to-noise a lone atom's significance is
    # about its peak over the noise times the root of its pixels in every view (hundreds), far
    # above the proof level (3.5 for 250 atoms); its depth fixed to a few pm, far inside half the
    # hard core. Both in the CSV too.
    assert np.all(atoms.arrays["proven"] == 1) and np.all(atoms.arrays["significance"] > 20)
    assert np.all(atoms.arrays["depth_open"] == 0) and np.all(atoms.arrays["depth_halfwidth_A"] < 0.1)
    header = (run / "atoms.csv").read_text().splitlines()[0].split(",")
    assert {"significance", "proven", "depth_halfwidth_A", "depth_open", "width_open", "trusted"} <= set(header)
    assert "; open: 0 not proven" in " ".join(train.stdout.split())
    # trusted: what nothing leaves open, one column (one element: no atom open in element)
    plain = (atoms.arrays["proven"] == 1) & (atoms.arrays["depth_open"] == 0) & (atoms.arrays["width_open"] == 0)
    assert np.array_equal(atoms.arrays["trusted"] == 1, plain)
    ev = _run(BIN / "gaussian-atoms", "evaluate", "--pred", run / "atoms.xyz", "--truth", data / "atoms_true.xyz")
    assert ev.returncode == 0, ev.stderr
    scores = json.loads(ev.stdout)
    # The run's own evaluation agrees (atoms.xyz keeps 1e-8 Å, so RMSD to 1e-6 pm).
    in_run = json.loads((run / "evaluation.json").read_text())
    run_only = {"converged", "steps"}  # how the run ended: the evaluate verb scores atoms alone
    assert in_run["converged"] is True and 0 < in_run["steps"] <= 3000
    from_positions = {"rmsd_pm", "precision_floor_A"}
    assert {k: v for k, v in in_run.items() if k not in run_only | from_positions} == {
        k: v for k, v in scores.items() if k not in from_positions
    }
    assert in_run["rmsd_pm"] == pytest.approx(scores["rmsd_pm"], abs=1e-6)
    # the floor is a quantile of sqrt((error / Z95)^2 - std^2), whose rounding grows by std / floor
    # where the two nearly cancel: atoms.xyz's 1e-8 Å reaches 2e-8 at a 0.7 pm floor (3 pm stds)
    assert in_run["precision_floor_A"] == pytest.approx(scores["precision_floor_A"], abs=1e-6)
    # Data made with the model's own physics at a peak-to-noise near 70 and every atom well
    # separated (2.9 Å vs 0.61 Å blur): every atom must be found, none invented, and positions
    # fixed far below the 0.25 Å pixel (noise-limited precision is a few pm).
    assert scores["n_true"] == len(truth) and len(atoms) == scores["n_pred"]
    assert scores["tpr"] == 1.0 and scores["fp_per_true_atom"] == 0.0
    assert scores["rmsd_pm"] < 5.0
    # The stated precision checked against the actual errors (gaussian-atoms check-precision): the
    # written statement read as evaluate and the run's own evaluation.json read it, one answer.
    check = _run(BIN / "gaussian-atoms", "check-precision", "--load-config", run / "config.yml")
    assert check.returncode == 0, check.stderr[-2000:]
    rows = [line.split("|") for line in check.stdout.splitlines() if line.count("|") == 9]
    rows = [r for r in rows if r[3].strip() in ("x", "y", "z")]
    assert [r[3].strip() for r in rows] == ["x", "y", "z"]
    assert all(0 < float(r[4]) < 5.0 and 0 < float(r[5]) < 5.0 for r in rows)
    assert [float(r[8]) for r in rows] == [round(c, 2) for c in in_run["coverage_95_xyz"]]
    assert [round(c, 2) for c in scores["coverage_95_xyz"]] == [round(c, 2) for c in in_run["coverage_95_xyz"]]
    # Widths come out near the true 0.61 Å (0.35 Å atom, 0.5 Å blur) in Å, not normalised units.
    assert 0.45 < atoms.arrays["sigma_A"].mean() < 0.8
    # The checkpoint loads back as ns-viewer / ns-eval load it (torch >= 2.6 weights_only
    # loading included), holding the atoms that were written.
    load = _run(
        sys.executable,
        "-c",
        (
            "import sys, numpy as np; from pathlib import Path; from nerfstudio.utils.eval_utils import eval_setup; "
            "_, pipe, _, step = eval_setup(Path(sys.argv[1]), test_mode='inference'); "
            "np.save(sys.argv[2], pipe.model.atoms().positions); print(step)"
        ),
        run / "config.yml",
        tmp_path / "loaded.npy",
        cwd=Path.cwd(),
    )
    assert load.returncode == 0, load.stderr[-3000:]
    np.testing.assert_allclose(np.load(tmp_path / "loaded.npy"), atoms.get_positions(), atol=1e-4)
    # ns-viewer on a run whose data has gone: one line naming the file, exit 2, no traceback.
    data.rename(tmp_path / "moved")
    viewer = subprocess.run(
        [str(BIN / "ns-viewer"), "--load-config", str(run / "config.yml")], capture_output=True, text=True, timeout=120
    )
    assert viewer.returncode == 2 and "Traceback" not in viewer.stderr
    assert f"{data}: data directory not found" in viewer.stderr


def test_cli_errors_are_one_line(tmp_path):
    ev = _run(BIN / "gaussian-atoms", "evaluate", "--pred", tmp_path / "none.xyz", "--truth", tmp_path / "none.xyz")
    assert ev.returncode == 2
    assert ev.stderr.strip().count("\n") == 0 and "none.xyz: atom file not found" in ev.stderr


def test_gaussian_atoms_train_is_ns_train(tmp_path, simulate_sphere):
    """`gaussian-atoms train` runs the same trainer with the same options as `ns-train
    gaussian-atoms`: on the CPU (deterministic, same seed) the same atoms to the last digit
    written, and a config.yml that differs only in the names given on the command line; a
    boolean option with the value False works in both."""
    data = tmp_path / "data"
    simulate_sphere(data, 5, "-70:10:70")
    runs = {}
    for name, launcher in (("ga", [BIN / "gaussian-atoms", "train"]), ("ns", [BIN / "ns-train", "gaussian-atoms"])):
        train = _run(
            *launcher,
            "--machine.device-type",
            "cpu",
            "--vis",
            "tensorboard",
            "--output-dir",
            tmp_path / "out",
            "--experiment-name",
            name,
            "--timestamp",
            "run",
            "--max-num-iterations",
            "300",
            "--pipeline.model.num-random",
            "400",
            "--pipeline.model.stop-when-converged",
            "False",
            "tilt-series",
            "--data",
            data,
        )
        assert train.returncode == 0, train.stdout[-3000:] + train.stderr[-3000:]
        runs[name] = tmp_path / "out" / name / "gaussian-atoms" / "run"
        if name == "ga":  # our lines and a progress bar, no configuration dump: it ends with what it found
            from gaussian_atoms_method.harness.input_cases import own_lines

            assert len(own_lines(train.stdout + train.stderr)) <= 60, train.stdout + train.stderr
            ending = " ".join(own_lines(train.stdout)[-4:])  # the console wraps its long last line
            assert "gaussian-atoms: against" in ending and ending.endswith("}") and "method_name=" not in train.stdout
    assert (runs["ga"] / "atoms.xyz").read_text() == (runs["ns"] / "atoms.xyz").read_text()
    # config.yml: ns-train's is nerfstudio's dump of its config; the engine's is a call that
    # builds that config when nerfstudio's loader reads it (engine/run_files.py): the same config.
    import yaml

    configs = [
        yaml.dump(yaml.load((runs[n] / "config.yml").read_text(), Loader=yaml.Loader))
        .replace(f"experiment_name: {n}", "")
        .replace(f"/{n}/", "/")
        for n in runs
    ]
    assert configs[0] == configs[1]
    # A boolean given a value, as nerfstudio's FlagConversionOff allows, means the same in both.
    assert "stop_when_converged: false" in configs[0]
    # The engine logs nerfstudio's loss, metrics and rates at nerfstudio's steps (not its timings
    # or evaluation images), through to the last step.
    ours, theirs = _scalar_steps(runs["ga"]), _scalar_steps(runs["ns"])
    assert "Train Loss" in ours and all(ours[tag] == theirs[tag] for tag in ours)
    assert max(max(steps) for steps in _scalar_steps(runs["ga"]).values()) >= 290
    # Bad input: one line naming the file; an option it cannot honour: named, with the way out.
    (tmp_path / "tilt_series.json").write_text('{"projections": "p.npy", "angles_deg": "a.txt", "pixel_size_A": 0.25}')
    bad = _run(
        BIN / "gaussian-atoms",
        "train",
        "--machine.device-type",
        "cpu",
        "--vis",
        "tensorboard",
        "--output-dir",
        tmp_path / "out",
        "tilt-series",
        "--data",
        tmp_path,
    )
    assert bad.returncode == 2 and "p.npy: projections file not found" in bad.stderr
    two = _run(
        BIN / "gaussian-atoms",
        "train",
        "--machine.num-devices",
        "2",
        "--output-dir",
        tmp_path / "out",
        "tilt-series",
        "--data",
        data,
    )
    assert two.returncode == 2 and "--machine.num-devices 2" in two.stderr and "ns-train" in two.stderr


def _scalar_steps(run: Path) -> dict:
    """Each scalar tag of the run's TensorBoard events and the steps it was logged at."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    (events,) = run.glob("events.out.tfevents.*")
    accumulator = EventAccumulator(str(events))
    accumulator.Reload()
    return {tag: [e.step for e in accumulator.Scalars(tag)] for tag in accumulator.Tags()["scalars"]}


def test_time_to_accuracy_benchmark(tmp_path, simulate_sphere):
    """`gaussian-atoms benchmark`: snapshots during training are scored next to FBP and SART;
    times increase, the written atoms (after the final stage) are the last row, files are written."""
    import csv

    data = tmp_path / "data"
    simulate_sphere(data, 5, "-70:10:70")
    out = tmp_path / "bench"
    bench = _run(
        BIN / "gaussian-atoms",
        "benchmark",
        "--data",
        data,
        "--output",
        out,
        "--iterations",
        "400",
        "--snapshot-every",
        "100",
    )
    assert bench.returncode == 0, bench.stdout[-3000:] + bench.stderr[-3000:]
    rows = list(csv.DictReader(open(out / "time_to_accuracy.csv")))
    assert [r["method"] for r in rows[:2]] == ["fbp", "sart"]
    ours = [r for r in rows if r["method"] == "ours"]
    assert [int(r["step"]) for r in ours] == [100, 200, 300, 400]
    seconds = [float(r["seconds"]) for r in ours]
    assert all(b > a for a, b in zip(seconds, seconds[1:])) and seconds[0] > 0
    final = rows[-1]
    assert final["method"] == "ours-final" and float(final["seconds"]) > seconds[0]
    # Model-physics data at peak-to-noise ~70: by the end every atom is found, none invented.
    assert float(final["tpr"]) == 1.0 and float(final["fp_per_true_atom"]) == 0.0
    assert (out / "time_to_accuracy.png").stat().st_size > 0 and (out / "time_to_accuracy.md").is_file()
