"""The front door: every broken tilt series stops in one line naming the file or option (exit
2, no traceback, no run directory), every odd but valid one trains, through both launchers."""

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from dataparsers.tilt_series_dataparser import TiltSeriesDataParserConfig
from gaussian_atoms_method.harness.input_cases import BROKEN, ODD
from gaussian_atoms_method.nerfstudio_layer.config import (
    INPUT_ERRORS,
    GaussianAtomsTrainer,
    check_input,
    gaussian_atoms_trainer_config,
)
from gaussian_atoms_method.nerfstudio_layer.launch import train_views
from gaussian_atoms_method.nerfstudio_layer.model import GaussianAtomsModelConfig

BIN = Path(sys.executable).parent


@pytest.mark.parametrize("name", list(BROKEN))
def test_broken_input_is_named_before_anything_runs(name, tmp_path):
    write, fragment = BROKEN[name]
    config = gaussian_atoms_trainer_config()
    config.pipeline.datamanager.data = write(tmp_path / "series")
    with pytest.raises(INPUT_ERRORS, match=None) as info:
        check_input(config)
    message = str(info.value)
    assert fragment in message and "\n" not in message


@pytest.mark.parametrize("name", list(ODD))
def test_odd_but_valid_input_trains(name, tmp_path):
    data = ODD[name](tmp_path / "series")
    config = gaussian_atoms_trainer_config()
    config.pipeline.datamanager.data = data
    check_input(config)
    outputs = TiltSeriesDataParserConfig(data=data).setup().get_dataparser_outputs("train")
    model = GaussianAtomsModelConfig(num_random=50).setup(
        scene_box=outputs.scene_box, num_train_data=len(outputs.cameras), metadata=outputs.metadata
    )
    targets = [outputs.metadata["projections"][v][..., None] for v in range(len(outputs.cameras))]
    loss = train_views(model, outputs.cameras, targets, steps=4)
    assert np.isfinite(loss) and all(bool(torch.isfinite(p).all()) for p in model.gauss_params.values())


def test_integer_counts_stay_integer_on_disk(tmp_path):
    """The odd case really is integer data (write_tilt_series itself stores float32)."""
    assert np.load(ODD["integer counts"](tmp_path) / "projections.npy").dtype == np.uint16


@pytest.mark.parametrize("launcher", [["ns-train", "gaussian-atoms"], ["gaussian-atoms", "train"]])
def test_launchers_stop_in_one_line_and_write_nothing(launcher, tmp_path):
    from gaussian_atoms_method.harness.input_matrix import run_case

    data = BROKEN["NaN pixels"][0](tmp_path / "series")
    out = tmp_path / "out"
    run, lines = run_case([str(BIN / launcher[0]), *launcher[1:]], data, out)
    assert run.returncode == 2 and "Traceback" not in run.stderr
    assert len(lines) == 1 and "projections.npy: projections hold 1 NaN/Inf value(s)" in lines[0], lines
    assert not out.exists()


def test_training_failure_is_one_line_with_step_and_cause(monkeypatch, capsys):
    """A non-finite loss (the model names the step and the cause) ends the run in one line."""
    from nerfstudio.engine.trainer import Trainer

    def diverge(self):
        raise FloatingPointError(
            "gaussian-atoms: step 17: the loss is nan and training cannot go on; cause: 3 Gaussian(s) with non-finite "
            "means."
        )

    monkeypatch.setattr(Trainer, "train", diverge)
    trainer = object.__new__(GaussianAtomsTrainer)
    with pytest.raises(SystemExit) as info:
        trainer.train()
    err = capsys.readouterr().err
    assert info.value.code == 1 and err.count("\n") == 1 and "step 17" in err and "non-finite means" in err


def test_the_default_device_is_one_this_machine_has():
    """Without --machine.device-type a run goes to the GPU where torch sees one, else the CPU
    (nerfstudio's own default, CUDA, stopped a CPU-only machine with a traceback)."""
    assert gaussian_atoms_trainer_config().machine.device_type == ("cuda" if torch.cuda.is_available() else "cpu")


def test_a_device_this_machine_lacks_is_named_in_one_line(monkeypatch, tmp_path):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    config = gaussian_atoms_trainer_config()
    config.pipeline.datamanager.data = ODD[next(iter(ODD))](tmp_path / "series")
    config.machine.device_type = "cuda"
    with pytest.raises(INPUT_ERRORS) as info:
        check_input(config)
    assert "--machine.device-type cuda" in str(info.value) and "\n" not in str(info.value)
    config.machine.device_type = "cpu"
    check_input(config)


@pytest.mark.parametrize(
    "argv, prog, named",
    [
        (["simulate", "--noise-std", "abc"], "gaussian-atoms simulate", "--noise-std"),
        (["film", "--output", "x", "--full-centre-vox", "1", "2"], "gaussian-atoms film", "--full-centre-vox"),
        (["simulat"], "gaussian-atoms", "simulat"),
        (  # the engine's own parse
            ["train", "--vis", "tensorboard", "--max-num-iterations", "abc", "tilt-series", "--data", "x"],
            "gaussian-atoms train",
            "--max-num-iterations",
        ),
        (  # an option the engine does not know: nerfstudio's parse
            ["train", "--vis", "tensorboard", "tilt-series", "--data", "x", "--bogus", "3"],
            "gaussian-atoms train",
            "--bogus",
        ),
    ],
)
def test_a_malformed_command_line_is_one_line_naming_the_option(argv, prog, named, capsys):
    from gaussian_atoms_method.cli import entrypoint

    with pytest.raises(SystemExit) as exit_info:
        entrypoint(argv)
    lines = [line for line in capsys.readouterr().err.splitlines() if "Warning" not in line and "warn" not in line]
    assert exit_info.value.code == 2 and len(lines) == 1, lines
    assert lines[0].startswith(f"{prog}: error: ") and named in lines[0] and f"{prog} --help" in lines[0]


def test_train_args_the_strips_fits_would_not_take_are_refused_in_one_line(tmp_path, capsys):
    """``benchmark-film --strips`` fits through ``reconstruct_film`` with the defaults: options for
    ``ns-train`` would not reach them, so they are named, before anything is fitted or written."""
    from gaussian_atoms_method.cli import entrypoint

    out = tmp_path / "bench"
    argv = ["benchmark-film", "--strips", "1", "--train-args=--pipeline.model.background plane", "--output", str(out)]
    with pytest.raises(SystemExit) as exit_info:
        entrypoint(argv)
    lines = [line for line in capsys.readouterr().err.splitlines() if "Warning" not in line and "warn" not in line]
    assert exit_info.value.code != 0 and len(lines) == 1 and "--train-args" in lines[0], lines
    assert not out.exists()


def test_help_still_reaches_the_user(capsys):
    from gaussian_atoms_method.cli import entrypoint

    with pytest.raises(SystemExit) as exit_info:
        entrypoint(["film", "--help"])
    assert exit_info.value.code == 0 and "--tasks-per-gpu" in capsys.readouterr().out


def test_a_parse_error_box_is_read_down_to_its_first_section():
    from gaussian_atoms_method.parse_errors import first_section

    box = (
        "╭─ Value error ─────────────────────────╮\n"
        "│ Error parsing --noise-std: could not  │\n"
        "│ convert string to float: 'abc'        │\n"
        "│ ───────────────────────────────────── │\n"
        "│ Argument helptext:                    │\n"
        "╰───────────────────────────────────────╯\n"
    )
    assert first_section(box) == "Error parsing --noise-std: could not convert string to float: 'abc'"
    plain = (  # rich's plain drawing of the same box (no terminal, as under pytest)
        " Value error \n ------------------ \n  Error parsing --noise-std: could not\n"
        "  convert string to float: 'abc' \n  ------------------\n  Argument helptext:\n"
    )
    assert first_section(plain) == "Error parsing --noise-std: could not convert string to float: 'abc'"
    assert first_section("usage: x\nerror: unrecognized arguments: --y\n") == "error: unrecognized arguments: --y"


def test_ns_train_says_a_malformed_command_line_in_one_line(tmp_path):
    import subprocess

    run = subprocess.run(
        [str(BIN / "ns-train"), "gaussian-atoms", "--max-num-iterations", "abc", "tilt-series", "--data", "x"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=300,
    )
    from gaussian_atoms_method.harness.input_matrix import own_lines

    lines = own_lines(run.stdout + run.stderr)  # less the warnings torch raises on nerfstudio's import
    assert run.returncode == 2 and len(lines) == 1, run.stderr
    assert lines[0].startswith("ns-train gaussian-atoms: error: ") and "--max-num-iterations" in lines[0]
    # torch.jit.script's note, raised as nerfstudio imports its cameras before any plugin loads, is
    # hidden by the start-up hook the install places (launch/quiet_warnings.py)
    warned = [line for line in (run.stdout + run.stderr).splitlines() if "Warning:" in line]
    assert not warned, warned


@pytest.mark.parametrize(
    "argv, quiet",
    [
        (["/venv/bin/ns-train", "gaussian-atoms", "--help"], True),
        (["C:\\venv\\Scripts\\ns-train.exe", "gaussian-atoms"], True),
        (["/venv/bin/ns-train", "nerfacto"], False),
        (["-c"], False),
        ([], False),
    ],
)
def test_the_start_up_hook_quiets_an_ns_train_run_of_gaussian_atoms_and_leaves_any_other_process(argv, quiet):
    """The install's ``gaussian_atoms_quiet.pth``, run as Python's ``site`` runs a line of a .pth
    that starts with ``import``, adds the launchers' warning filters only where the command line
    is ``ns-train gaussian-atoms``."""
    import warnings

    hook = (Path(__file__).parents[1] / "gaussian_atoms_method" / "launch" / "gaussian_atoms_quiet.pth").read_text()
    lines = [line for line in hook.splitlines() if line.startswith("import")]
    assert len(lines) == 1
    saved = sys.argv
    with warnings.catch_warnings():
        before = list(warnings.filters)
        sys.argv = argv
        try:
            exec(lines[0], {})
        finally:
            sys.argv = saved
        assert (warnings.filters != before) == quiet


def test_third_party_deprecations_are_hidden_in_a_launchers_process_and_a_users_own_still_show():
    import subprocess

    code = (
        "import types, warnings\n"
        "from gaussian_atoms_method.launch.quiet_warnings import quiet_third_party_warnings\n"
        "quiet_third_party_warnings()\n"
        "theirs = types.ModuleType('nerfstudio.fake')\n"
        "exec(\"import warnings\\nwarnings.warn('theirs', FutureWarning)\", theirs.__dict__)\n"
        "warnings.warn('mine', FutureWarning)\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert "mine" in run.stderr and "theirs" not in run.stderr


def test_gaussian_atoms_train_starts_no_viewer_unless_asked():
    """``gaussian-atoms train`` without ``--vis`` runs the engine (TensorBoard's event file, no
    viewer left serving); ``--vis viewer`` goes to nerfstudio's trainer, which serves one."""
    from gaussian_atoms_method.cli.train_command import engine_runs
    from gaussian_atoms_method.nerfstudio_layer.launch import build_config

    assert engine_runs(["tilt-series", "--data", "data/demo"])
    assert not engine_runs(["--vis", "viewer", "tilt-series", "--data", "data/demo"])
    assert build_config(["tilt-series", "--data", "data/demo"]).vis == "tensorboard"


def test_a_viewer_left_serving_says_where_and_how_to_stop_it(capfd):
    """Once the results are written, a run whose viewer keeps serving says its address and
    Ctrl-C; one whose viewer quits with training, or before its last step, says nothing."""
    from types import SimpleNamespace

    from gaussian_atoms_method.nerfstudio_layer.model import GaussianAtomsModel, TrainingSpan

    model = SimpleNamespace(kernel_reading=SimpleNamespace(first_pass=False))
    span = TrainingSpan(3000)
    viewer = SimpleNamespace(viewer_info=["Viewer running locally at: http://127.0.0.1:7007"])

    def trainer(quit_after: bool, stopped: bool):
        config = SimpleNamespace(viewer=SimpleNamespace(quit_on_train_completion=quit_after))
        return SimpleNamespace(viewer_state=viewer, config=config, stop_training=stopped)

    GaussianAtomsModel._say_viewer(model, trainer(False, False), span, 1500)
    GaussianAtomsModel._say_viewer(model, trainer(True, True), span, 1500)
    assert "viewer" not in capfd.readouterr().out
    GaussianAtomsModel._say_viewer(model, trainer(False, True), span, 1500)
    said = capfd.readouterr().out
    assert "http://127.0.0.1:7007" in said and "Ctrl-C" in said


def test_train_help_is_this_methods_options_in_plain_text(capsys):
    """``gaussian-atoms train --help``: at most 250 lines, every fit and tilt-series option with
    its default, no Sphinx markup, no other package's dataparsers."""
    import dataclasses

    from dataparsers.tilt_series_options import TiltSeriesOptions
    from gaussian_atoms_method.cli import entrypoint
    from gaussian_atoms_method.engine.options import FitOptions

    entrypoint(["train", "--help"])
    text = capsys.readouterr().out
    assert len(text.splitlines()) <= 250
    assert not any(role in text for role in (":func:", ":class:", ":data:", ":meth:", ":mod:", "``", "::\n"))
    assert "blender-data" not in text and "colmap" not in text
    for f in dataclasses.fields(FitOptions):
        if f.init and not f.name.startswith("_"):
            assert f"--pipeline.model.{f.name.replace('_', '-')} " in text, f.name
    for f in dataclasses.fields(TiltSeriesOptions):
        assert f"--{f.name.replace('_', '-')} " in text, f.name


def test_the_fits_options_bring_their_own_help_over_splatfactos():
    """An option splatfacto also has (``refine_every``, ``warmup_length``, ...) shows the fit's
    docstring, read from FitOptions' source (``field_docs``) and cleaned, and the fit's default;
    a field without a docstring has none."""
    import dataclasses
    import inspect

    from gaussian_atoms_method.engine.options import FitOptions, field_docs
    from gaussian_atoms_method.nerfstudio_layer.options import (
        GaussianAtomsOptions,
        SplatfactoModelConfig,
        fit_fields_over_splatfacto,
    )

    shared, docs = fit_fields_over_splatfacto(), field_docs(FitOptions)
    assert "refine_every" in shared and set(shared) <= {f.name for f in dataclasses.fields(SplatfactoModelConfig)}
    for name, (hint, _field) in shared.items():
        help_text = hint.__metadata__[0].help
        assert help_text and help_text == inspect.cleandoc(docs[name]), name
        assert getattr(GaussianAtomsOptions(), name) == getattr(FitOptions(), name), name
    assert inspect.cleandoc(docs["refine_every"]) == "Steps between densify / prune / merge."

    @dataclasses.dataclass
    class Plain:
        x: int = 1
        y: int = 2
        """Why y."""

    assert field_docs(Plain) == {"y": "Why y."}


def test_a_training_loops_last_step_is_read_from_its_first():
    """nerfstudio's loop runs ``max_num_iterations`` steps from its start (past 0 when resumed
    from a checkpoint): the last step the results are written at is the first step seen plus
    the iterations less one, whatever the steps seen after it."""
    from gaussian_atoms_method.nerfstudio_layer.model import TrainingSpan

    fresh, resumed = TrainingSpan(300), TrainingSpan(300)
    assert fresh.last == 299
    for step in (0, 1, 2):
        fresh.see(step=step)
    for step in (1000, 1001):
        resumed.see(step=step)
    assert (fresh.first, fresh.last) == (0, 299) and (resumed.first, resumed.last) == (1000, 1299)


def test_the_nerfstudio_launchers_decide_registration_before_config_is_saved(tmp_path, capfd):
    """``--pipeline.model.decide-registration`` under ``ns-train`` (and ``gaussian-atoms train``'s
    nerfstudio path): the input check runs the four trial fits on the series it read and leaves
    the model's ``refine_alignment`` and ``refine_gain`` set to the choice, so the config.yml
    nerfstudio then saves records it; the trial fits' own config.yml take the fit's options alone
    (splatfacto's camera optimiser is not one yaml can write)."""
    from gaussian_atoms_method.harness.input_cases import valid_series

    config = gaussian_atoms_trainer_config(max_iterations=100)
    config.machine.device_type = "cpu"
    config.pipeline.datamanager.data = valid_series(tmp_path / "series")
    config.pipeline.model.decide_registration = True
    config.check_or_exit()
    said = capfd.readouterr().out
    from gaussian_atoms_method.engine.run import REGISTRATION

    chosen = said.split("per-view registration: ")[1].split(" (")[0]
    model = config.pipeline.model
    assert not model.decide_registration and (model.refine_alignment, model.refine_gain) == REGISTRATION[chosen]


def test_the_film_benchmark_says_its_specimen_is_a_film_unless_told_otherwise():
    """``benchmark-film`` runs each sub-area with the extended object on (the specimen is a film,
    which the views' gains can hide from the views' mass): the options parse as the train
    command's, and an extended-object option the user gives replaces it."""
    from gaussian_atoms_method.cli.train_command import parse
    from gaussian_atoms_method.harness.film_benchmark import FilmBenchmark

    def extended_object(flags):
        bench = FilmBenchmark(Path("data"), Path("out"), flags=flags)
        options, _ = parse([*bench.film_flags(), "tilt-series", "--data", "data/demo"])
        return options.pipeline.model.extended_object

    assert extended_object(()) == "on"
    assert extended_object(("--pipeline.model.cluster-merge", "False")) == "on"
    assert extended_object(("--pipeline.model.extended-object", "auto")) == "auto"
    assert extended_object(("--pipeline.model.extended-object=off",)) == "off"


def test_a_console_counts_a_progress_bars_redrawings_as_the_one_line_a_terminal_shows():
    """The console's length is what a terminal shows: a bar redrawn after carriage returns is one
    line, and a nested bar (drawn on the line below, the cursor moved back up after each
    drawing) is its last drawing; the FutureWarnings of an import and their source lines are not
    ours."""
    from gaussian_atoms_method.harness.input_cases import own_lines

    text = (
        "gaussian-atoms: start\nx.py:3: FutureWarning: old\n  import y\n"
        "\rsteps 10%\rsteps 50%\n\revidence 20%\x1b[A\n\revidence 60%\x1b[A\nevidence 100%\n\rsteps 100%\ndone"
    )
    assert own_lines(text) == ["gaussian-atoms: start", "steps 50%", "evidence 100%", "steps 100%", "done"]
