"""``gaussian-atoms train``: the engine's run (:mod:`gaussian_atoms_method.engine.run`) from the
options of ``ns-train gaussian-atoms``, with no nerfstudio import.

The command line is nerfstudio's (``[trainer and model options] tilt-series --data DIR
[tilt-series options]``), read here by :class:`TrainOptions`, a copy of the part of
nerfstudio's trainer config that a run on one device with TensorBoard logging uses.  What only
nerfstudio's trainer does goes to it (:func:`engine_runs` says which): the viewer while
training (``--vis viewer``, nerfstudio's default), wandb or comet, a loaded config or
checkpoint, other optimiser settings, several devices, and ``--help``, which lists every option.
Both give the same atoms, run directory and files.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional

from dataparsers.tilt_series_options import TiltSeriesOptions
from gaussian_atoms_method.engine.options import FitOptions
from gaussian_atoms_method.engine.run import MAX_ITERATIONS
from gaussian_atoms_method.engine.run_files import SEED
from gaussian_atoms_method.physics.devices import default_device

SUBCOMMAND = "tilt-series"


@dataclass
class MachineOptions:
    seed: int = SEED
    """Seed of Python's, NumPy's and torch's generators."""
    device_type: Literal["cpu", "cuda", "mps"] = field(default_factory=default_device)
    """Where to train (default: the GPU where torch sees one)."""


@dataclass
class LocalWriterOptions:
    enable: bool = True
    """The progress bar (nerfstudio: its table of steps)."""


@dataclass
class LoggingOptions:
    local_writer: LocalWriterOptions = field(default_factory=LocalWriterOptions)
    steps_per_log: int = 10
    """Steps between TensorBoard scalars."""


@dataclass
class DatamanagerOptions:
    data: Optional[Path] = None
    """The tilt series (overrides tilt-series --data)."""


@dataclass
class PipelineOptions:
    datamanager: DatamanagerOptions = field(default_factory=DatamanagerOptions)
    model: FitOptions = field(default_factory=FitOptions)


@dataclass
class TrainOptions:
    """``ns-train gaussian-atoms``'s options that the engine's run takes (the same names)."""

    output_dir: Path = Path("outputs")
    experiment_name: Optional[str] = None
    timestamp: str = "{timestamp}"
    max_num_iterations: int = MAX_ITERATIONS
    steps_per_save: int = 1000
    vis: Literal["tensorboard"] = "tensorboard"
    data: Optional[Path] = None
    machine: MachineOptions = field(default_factory=MachineOptions)
    logging: LoggingOptions = field(default_factory=LoggingOptions)
    pipeline: PipelineOptions = field(default_factory=PipelineOptions)


def flags(cls, prefix: str = "") -> set[str]:
    """The command line's option names for dataclass ``cls`` (dots between levels, hyphens
    within names)."""
    out = set()
    for f in dataclasses.fields(cls):
        if f.name.startswith("_"):
            continue
        name = prefix + f.name.replace("_", "-")
        default = f.default_factory() if f.default is dataclasses.MISSING else f.default
        if dataclasses.is_dataclass(default):
            out |= flags(type(default), name + ".")
        else:
            out.add(name)
    return out


def split_at_subcommand(argv: list[str]) -> tuple[list[str], list[str]]:
    """The trainer's options and the tilt series' (after ``tilt-series``)."""
    if SUBCOMMAND in argv:
        cut = argv.index(SUBCOMMAND)
        return argv[:cut], argv[cut + 1 :]
    return argv, []


def given_flags(argv: list[str]) -> list[tuple[str, str | None]]:
    """Each ``--name`` in ``argv`` with the word after it (None at the end)."""
    out = []
    for i, word in enumerate(argv):
        if word.startswith("--"):
            name, _, value = word[2:].partition("=")
            out.append((name.replace("_", "-"), value or (argv[i + 1] if i + 1 < len(argv) else None)))
    return out


def engine_runs(argv: list[str]) -> bool:
    """True where the engine runs ``gaussian-atoms train ARGV`` as nerfstudio's trainer would:
    ``--vis tensorboard`` (this command's default) and every option one :class:`TrainOptions` or the tilt-series options
    know (else nerfstudio's trainer runs it)."""
    trainer, tilt = split_at_subcommand(argv)
    if any(word in ("-h", "--help") for word in argv):
        return False
    given = given_flags(trainer)
    if dict(given).get("vis", "tensorboard") != "tensorboard":  # a viewer only when asked (--vis viewer)
        return False
    return {n for n, _ in given} <= flags(TrainOptions) and {n for n, _ in given_flags(tilt)} <= flags(
        TiltSeriesOptions
    )


def parse(argv: list[str]) -> tuple[TrainOptions, TiltSeriesOptions]:
    """The options of ``gaussian-atoms train ARGV`` (one line and exit 2 for a malformed command
    line, :func:`~gaussian_atoms_method.parse_errors.one_line_errors`)."""
    import tyro

    from gaussian_atoms_method.parse_errors import one_line_errors

    trainer, tilt = split_at_subcommand(argv)
    # booleans take a value, as ns-train's (--pipeline.model.cluster-merge False)
    with one_line_errors("gaussian-atoms train"):
        options = tyro.cli(
            TrainOptions, args=trainer, config=(tyro.conf.FlagConversionOff,), prog="gaussian-atoms train"
        )
    with one_line_errors(f"gaussian-atoms train {SUBCOMMAND}"):
        series = tyro.cli(
            TiltSeriesOptions,
            args=tilt,
            config=(tyro.conf.FlagConversionOff,),
            prog=f"gaussian-atoms train {SUBCOMMAND}",
        )
    return options, series


def check(options: TrainOptions, tilt: TiltSeriesOptions, settings):
    """The tilt series, read; raises the input errors naming the file or option, as
    ``ns-train``'s check does before anything is written."""
    from gaussian_atoms_method.atoms.atom_set import read_atoms
    from gaussian_atoms_method.engine.run import check_settings

    check_settings(settings)
    options.pipeline.model.check()
    series = tilt.load(data_of(options, tilt))
    if series.truth_path is not None:
        read_atoms(series.truth_path)
    return series


def data_of(options: TrainOptions, tilt: TiltSeriesOptions) -> Path:
    """The tilt series' path: ``--data``, ``--pipeline.datamanager.data`` or the tilt series' own."""
    return options.data or options.pipeline.datamanager.data or tilt.data


def run(argv: list[str]) -> None:
    """Parse, check and run ``gaussian-atoms train ARGV`` on the engine; end the process (0, or
    one line and 2 for bad input, 1 for a failure in training, 130 for Ctrl+C)."""
    from dataparsers.errors import TiltSeriesError
    from gaussian_atoms_method.atoms.atom_set import AtomFileError
    from gaussian_atoms_method.engine.errors import OptionError
    from gaussian_atoms_method.engine.run import RunSettings, fit_tilt_series
    from gaussian_atoms_method.engine.run_files import RunPlace, options_dict
    from gaussian_atoms_method.launch.lean_torch import lean_torch
    from gaussian_atoms_method.launch.process_exit import exit_process, fail
    from gaussian_atoms_method.launch.start_ahead import prepared

    options, tilt = parse(argv)
    settings = RunSettings(
        RunPlace(options.output_dir, options.experiment_name, options.timestamp),
        options.machine.device_type,
        options.max_num_iterations,
        MAX_ITERATIONS,  # as ns-train: the schedule is the config's, not --max-num-iterations
        options.machine.seed,
        options.logging.local_writer.enable,
        True,
        options.steps_per_save,
        options.logging.steps_per_log,
    )
    try:
        series = check(options, tilt, settings)
    except (TiltSeriesError, AtomFileError, OptionError) as exc:
        fail(f"gaussian-atoms: error: {exc}", 2)
    dataparser = {k: v for k, v in options_dict(tilt).items() if k != "data"}
    lean_torch()  # the launcher's own process: torch's compiler front end and symbolic shapes stay unimported
    try:
        fit_tilt_series(series, options.pipeline.model, settings, data_of(options, tilt), dataparser, prepared())
    except FloatingPointError as exc:  # the fit names the step and the cause
        fail(str(exc), 1)
    except KeyboardInterrupt:  # results are written at the end only: none half-written
        fail("gaussian-atoms: interrupted", 130)
    exit_process(0)
