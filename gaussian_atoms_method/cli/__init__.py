"""``gaussian-atoms <verb>``: one tyro CLI whose verbs call the physics core.

Verbs: ``simulate`` (write a tilt-series directory with known atoms), ``evaluate`` (score
predicted atoms against the truth), ``baseline`` (FBP/SART + atom tracing), the benchmarks,
``stress``, ``export`` and ``sweep``.  Training is ``ns-train gaussian-atoms`` or, with
the same options, ``gaussian-atoms train``, which runs the engine without nerfstudio where
nerfstudio's trainer is not needed (:mod:`.train_command`).
"""

from __future__ import annotations

import os
import sys
import typing
from typing import Annotated, Union

import tyro

from gaussian_atoms_method.cli.benchmark_verbs import (
    Baseline,
    Benchmark,
    BenchmarkAccuracy,
    BenchmarkFilm,
    BenchmarkPeer,
    Stress,
    Sweep,
    split_grid,
)
from gaussian_atoms_method.cli.data_verbs import Evaluate, Export, Simulate, Train, View
from gaussian_atoms_method.cli.film_verb import Film
from gaussian_atoms_method.cli.tool_verbs import CheckPrecision, HeldOutViews, InputMatrix, InternalFloor, Screenshot
from gaussian_atoms_method.parse_errors import one_line_errors

Commands = Union[
    Annotated[Train, tyro.conf.subcommand("train")],
    Annotated[Simulate, tyro.conf.subcommand("simulate")],
    Annotated[Evaluate, tyro.conf.subcommand("evaluate")],
    Annotated[Baseline, tyro.conf.subcommand("baseline")],
    Annotated[Benchmark, tyro.conf.subcommand("benchmark")],
    Annotated[BenchmarkAccuracy, tyro.conf.subcommand("benchmark-accuracy")],
    Annotated[BenchmarkPeer, tyro.conf.subcommand("benchmark-peer")],
    Annotated[BenchmarkFilm, tyro.conf.subcommand("benchmark-film")],
    Annotated[Stress, tyro.conf.subcommand("stress")],
    Annotated[Export, tyro.conf.subcommand("export")],
    Annotated[View, tyro.conf.subcommand("view")],
    Annotated[Film, tyro.conf.subcommand("film")],
    Annotated[Sweep, tyro.conf.subcommand("sweep")],
    Annotated[HeldOutViews, tyro.conf.subcommand("held-out-views")],
    Annotated[CheckPrecision, tyro.conf.subcommand("check-precision")],
    Annotated[InternalFloor, tyro.conf.subcommand("internal-floor")],
    Annotated[InputMatrix, tyro.conf.subcommand("input-matrix")],
    Annotated[Screenshot, tyro.conf.subcommand("screenshot")],
]

VERBS = tuple(m.name for verb in typing.get_args(Commands) for m in verb.__metadata__ if hasattr(m, "name"))
"""The verbs' names, as the command line spells them."""


def parse(argv: list[str]) -> object:
    """What ``gaussian-atoms ARGV`` would run, built but not run: for ``train`` the engine's
    options (:func:`.train_command.parse`), or nerfstudio's TrainerConfig where nerfstudio's
    trainer runs it (:func:`.train_command.engine_runs`), otherwise the verb's dataclass
    (a sweep with its grid, ns-train's own options passed through after "--")."""
    if argv[:1] == ["train"]:
        from gaussian_atoms_method.cli import train_command

        if train_command.engine_runs(argv[1:]):
            return train_command.parse(argv[1:])
        from gaussian_atoms_method.nerfstudio_layer.launch import build_config

        with one_line_errors("gaussian-atoms train"):
            return build_config(argv[1:])
    grid: tuple[str, ...] = ()
    if argv[:1] == ["sweep"] and "--" in argv:
        cut = argv.index("--")
        argv, grid = argv[:cut], split_grid(argv[cut + 1 :])
    verb = f"gaussian-atoms {argv[0]}" if argv and argv[0] in VERBS else "gaussian-atoms"
    with one_line_errors(verb):
        command = tyro.cli(Commands, args=argv)
    if isinstance(command, Sweep):
        command.grid = grid
    return command


IDLE_THREADS = ("GOMP_SPINCOUNT", "5000")
"""OpenMP's idle workers spin 5,000 times, then sleep (set before torch loads; a wait policy or
spin count the user's environment gives wins).  Spinning without end (torch's default, 300,000)
takes the cores a second fit on the machine needs: two demo fits at once took 15 times one alone;
sleeping at once (``OMP_WAIT_POLICY=PASSIVE``) wakes a worker by a system call at each of a step's
parallel operations: the Au noise-200 run took 115 s against 80 s, a fifth of it system time.  At
5,000 spins the same run takes 86 s (10% system time) and two demo fits at once 2.8 times one
alone, as long as when sleeping at once (``scripts/studies/two_fits.py``, this 2-core CPU)."""


def spin_briefly(environ) -> None:
    """Set :data:`IDLE_THREADS` in ``environ`` (a mapping such as ``os.environ``) unless it
    gives OpenMP's wait policy or spin count itself."""
    if "OMP_WAIT_POLICY" not in environ and "GOMP_SPINCOUNT" not in environ:
        environ[IDLE_THREADS[0]] = IDLE_THREADS[1]


def entrypoint(argv: list[str] | None = None) -> None:
    """Run one verb; errors in the user's input are reported in one line, exit status 2."""
    spin_briefly(os.environ)  # this command's own process: before torch is imported
    from gaussian_atoms_method.launch.host_pages import keep_freed_memory, ordinary_pages
    from gaussian_atoms_method.launch.quiet_warnings import quiet_third_party_warnings

    quiet_third_party_warnings()
    ordinary_pages()  # this command's own process (launch/host_pages.py)
    keep_freed_memory()
    from dataparsers.tilt_series_format import TiltSeriesError
    from gaussian_atoms_method.atoms.atom_set import AtomFileError

    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["train"] and any(word in ("-h", "--help") for word in argv[1:]):
        from gaussian_atoms_method.cli.train_help import train_help

        print(train_help())  # this method's options; ns-train gaussian-atoms --help lists nerfstudio's too
        return
    if argv[:1] == ["train"]:
        from gaussian_atoms_method.launch import cuda_context
        from gaussian_atoms_method.launch.start_ahead import begin_for, end_now, runs_on_cuda, settle_imports

        if runs_on_cuda(argv[1:]):
            cuda_context.begin()  # the GPU's context made while torch imports
        if begin_for(argv[1:]):  # the start computed in a thread while the launcher loads
            import torch  # noqa: F401 - first: the thread imports scipy's packages meanwhile

            settle_imports()  # before the engine imports them too
        from gaussian_atoms_method.cli import train_command

        if train_command.engine_runs(argv[1:]):
            try:
                train_command.run(argv[1:])
            except SystemExit as exc:  # the command line's own errors, said by tyro
                end_now(exc.code if isinstance(exc.code, int) else 2)
                raise
        from gaussian_atoms_method.nerfstudio_layer.config import INPUT_ERRORS
        from gaussian_atoms_method.nerfstudio_layer.launch import exit_process
        from gaussian_atoms_method.nerfstudio_layer.launch import run as train_run

        try:
            config = parse(argv)
        except SystemExit as exc:  # the command line's own errors (and --help), said by tyro
            end_now(exc.code if isinstance(exc.code, int) else 2)
            raise
        try:
            train_run(config)
        except INPUT_ERRORS as exc:
            print(f"gaussian-atoms train: error: {exc}", file=sys.stderr)
            end_now(2)
            raise SystemExit(2) from None
        exit_process(0)  # the run's files are complete: no teardown of what it loaded
    command = parse(argv)
    from gaussian_atoms_method.film.film import FilmError

    try:
        command.main()
    except (TiltSeriesError, AtomFileError, ValueError, FileNotFoundError) as exc:
        print(f"gaussian-atoms: error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    except FilmError as exc:  # sub-areas failed; the others' fits are kept for a resume
        print(f"gaussian-atoms film: error: {exc}", file=sys.stderr)
        raise SystemExit(1) from None
