"""Config sweeps: one ``ns-train gaussian-atoms`` run per point of a grid of tyro overrides.

A grid entry is an option and its values, as typed on the command line::

    "--pipeline.model.merge-threshold-A 0.2 0.3 0.5"

Every combination of the entries' values is one run, in its own directory named by the
settings.  A run that finished (its ``result.json`` holds the same settings) is not run
again, so an interrupted sweep resumes where it stopped.  Runs go to local processes (up to
``jobs`` at a time, the machine's threads shared between them) or to a Ray cluster
(``backend="ray"``, the optional ``ray`` extra).  With a truth file in the tilt-series
directory each run is scored against it.  One table, ``sweep.csv`` and ``sweep.md``, holds
settings against metrics and wall time.
"""

from __future__ import annotations

import csv
import hashlib
import itertools
import json
import re
import shlex
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Literal, Optional

METRICS = ["tpr", "fp_per_true_atom", "rmsd_pm", "n_pred", "n_true", "seconds"]


class SweepError(ValueError):
    """A sweep option is malformed: names the option and what was expected."""


def parse_grid(entries) -> list[tuple[str, list[str]]]:
    """``["--opt v1 v2", ...]`` -> ``[("--opt", ["v1", "v2"]), ...]``, checked."""
    grid = []
    for entry in entries:
        words = shlex.split(entry)
        if len(words) < 2 or not words[0].startswith("--"):
            raise SweepError(
                f"sweep grid {entry!r}: expected an ns-train option and at least one value, e.g. "
                f"'--pipeline.model.merge-threshold-A 0.2 0.3'"
            )
        if any(words[0] == option for option, _ in grid):
            raise SweepError(f"sweep grid: {words[0]} is given twice")
        grid.append((words[0], words[1:]))
    if not grid:
        raise SweepError("sweep grid: give ns-train options and their values after '--'")
    return grid


def grid_settings(grid: list[tuple[str, list[str]]]) -> list[dict[str, str]]:
    """Every combination of the grid's values, as ``{option: value}`` in grid order."""
    options = [option for option, _ in grid]
    return [dict(zip(options, values)) for values in itertools.product(*(values for _, values in grid))]


def run_name(settings: dict[str, str]) -> str:
    """A readable, filesystem-safe directory name that is unique for the settings."""
    short = "_".join(f"{option.rsplit('.', 1)[-1].lstrip('-')}={value}" for option, value in settings.items())
    short = re.sub(r"[^A-Za-z0-9_.=+-]", "-", short)[:80]
    digest = hashlib.sha1(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:8]
    return f"{short}_{digest}"


def train_and_score(data: str, run_dir: str, args: list[str], iterations: int, device: str, threads: int) -> dict:
    """Train one run in a subprocess and score it against the data's truth, if any.

    A plain function of strings and numbers so that Ray can ship it to another machine.
    """
    import time

    from gaussian_atoms_method.harness.benchmark import train_ours
    from gaussian_atoms_method.harness.evaluation import evaluate_atoms, load_reference

    start = time.time()
    pred, seconds = train_ours(Path(data), Path(run_dir), iterations, device, tuple(args), threads)
    result = {"seconds": seconds, "n_pred": len(pred), "finished_unix": time.time(), "started_unix": start}
    try:
        _, truth, _, _ = load_reference(Path(data))
    except ValueError:  # no truth file: the table shows counts and times only
        return result
    scores = evaluate_atoms(pred, truth)
    result.update({k: scores[k] for k in ("tpr", "fp_per_true_atom", "rmsd_pm", "n_true")})
    return result


@dataclass
class SweepOptions:
    """A sweep's options, declared once: the :class:`Sweep` here and the command
    ``gaussian-atoms sweep`` take them."""

    data: Path
    """Tilt-series directory (with a truth file the runs are scored)."""
    output: Path = Path("outputs/sweep")
    iterations: int = 3000
    jobs: int = 1
    """Runs at a time (local backend); the machine's threads are shared between them."""
    device: Literal["cpu", "cuda"] = "cpu"
    backend: Literal["local", "ray"] = "local"
    """local processes, or a Ray cluster (pip install 'gaussian-atoms[ray]')."""
    ray_address: Optional[str] = None
    """Address of an existing Ray cluster (default: start a local one)."""
    grid: tuple[str, ...] = ()
    """Each entry an option and its values, as typed: ``"--pipeline.model.merge-threshold-A 0.2 0.3"``."""


@dataclass
class Sweep(SweepOptions):
    """The runs of a grid (:class:`SweepOptions`), each with ``base_args`` before its settings,
    through ``runner`` (a test's stand-in; by default :func:`train_and_score`)."""

    base_args: tuple[str, ...] = ()
    runner: Callable[..., dict] = field(default=train_and_score, repr=False)

    def __post_init__(self) -> None:
        self.data, self.output = Path(self.data), Path(self.output)
        if not (self.data / "tilt_series.json").is_file() and not self.data.is_file():
            raise SweepError(f"--data {self.data}: expected a tilt-series directory with tilt_series.json")
        if self.jobs < 1:
            raise SweepError(f"--jobs {self.jobs}: expected at least 1")
        if self.backend not in ("local", "ray"):
            raise SweepError(f"--backend {self.backend!r}: expected local or ray")
        grid = parse_grid(self.grid)
        self.options = [option for option, _ in grid]
        self.settings = grid_settings(grid)

    def _args(self, settings: dict[str, str]) -> list[str]:
        return [*self.base_args, *itertools.chain.from_iterable(settings.items())]

    def _finished(self, run_dir: Path, settings: dict[str, str]) -> dict | None:
        path = run_dir / "result.json"
        if not path.is_file():
            return None
        saved = json.loads(path.read_text())
        same = (
            saved.get("settings") == settings
            and saved.get("base_args") == list(self.base_args)
            and saved.get("iterations") == self.iterations
        )
        return saved if same else None

    def run(self) -> list[dict]:
        """Run what is not finished yet; return one row per setting and write the table."""
        self.output.mkdir(parents=True, exist_ok=True)
        rows: list[dict | None] = []
        todo = []
        for settings in self.settings:
            run_dir = self.output / "runs" / run_name(settings)
            done = self._finished(run_dir, settings)
            rows.append(done)
            if done is None:
                todo.append((len(rows) - 1, settings, run_dir))
        print(
            f"gaussian-atoms sweep: {len(self.settings)} settings, {len(self.settings) - len(todo)} already finished, "
            f"{len(todo)} to run"
        )
        from gaussian_atoms_method.physics.devices import threads_given

        threads = max(1, threads_given() // min(self.jobs, max(len(todo), 1)))  # the cores given, shared
        calls = [
            (str(self.data), str(run_dir), self._args(settings), self.iterations, self.device, threads)
            for _, settings, run_dir in todo
        ]

        def finish(k: int, outcome) -> None:
            # Recorded as each run ends, so an interruption loses only the runs in flight.
            index, settings, run_dir = todo[k]
            if isinstance(outcome, BaseException):
                # One failed setting does not stop the sweep; the table says why it failed.
                print(f"gaussian-atoms sweep: {run_dir.name} failed: {str(outcome)[-500:]}")
                first_line = str(outcome).splitlines()[0][:120] if str(outcome) else type(outcome).__name__
                rows[index] = {"settings": settings, "status": f"failed: {first_line}"}
                return
            row = {
                "settings": settings,
                "base_args": list(self.base_args),
                "iterations": self.iterations,
                "status": "ok",
                **outcome,
            }
            run_dir.mkdir(parents=True, exist_ok=True)
            tmp = run_dir / "result.json.tmp"
            tmp.write_text(json.dumps(row, indent=2) + "\n")
            tmp.replace(run_dir / "result.json")  # complete or absent: resume trusts it
            rows[index] = row
            print(f"gaussian-atoms sweep: finished {run_dir.name}")

        if self.backend == "ray":
            self._run_ray(calls, finish)
        else:
            self._run_local(calls, finish)
        self.write(rows)
        return rows

    def _run_local(self, calls, finish) -> None:
        def call(c):
            try:
                return self.runner(*c)
            except Exception as exc:  # reported per run
                return exc

        pool = ThreadPoolExecutor(max_workers=self.jobs)
        try:
            futures = {pool.submit(call, c): k for k, c in enumerate(calls)}
            for future in as_completed(futures):
                finish(futures[future], future.result())
        finally:
            # On an interruption, start nothing more (runs in flight get the signal too).
            pool.shutdown(wait=True, cancel_futures=True)

    def _run_ray(self, calls, finish) -> None:
        try:
            import ray
        except ImportError as exc:
            raise SweepError("--backend ray: Ray is not installed (pip install 'gaussian-atoms[ray]')") from exc
        if not calls:
            return
        if not ray.is_initialized():
            ray.init(address=self.ray_address, include_dashboard=False, log_to_driver=False)
        remote = ray.remote(num_cpus=calls[0][5])(self.runner)
        pending = {remote.remote(*c): k for k, c in enumerate(calls)}
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            k = pending.pop(done[0])
            try:
                finish(k, ray.get(done[0]))
            except Exception as exc:  # the run raised on its worker
                finish(k, exc)

    def write(self, rows: list[dict]) -> None:
        options = self.options
        header = [o.lstrip("-") for o in options] + METRICS + ["status", "run"]
        table = []
        for settings, row in zip(self.settings, rows):
            table.append(
                [settings[o] for o in options]
                + [_fmt(row.get(m)) for m in METRICS]
                + [row.get("status", ""), run_name(settings)]
            )
        with open(self.output / "sweep.csv", "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(header)
            writer.writerows(table)
        md = (
            f"Sweep on `{self.data}`, {self.iterations} iterations, base arguments "
            f"`{' '.join(self.base_args) or '(none)'}`.\n\n"
        )
        md += "| " + " | ".join(header[:-1]) + " |\n|" + " --- |" * (len(header) - 1) + "\n"
        md += "".join("| " + " | ".join(map(str, r[:-1])) + " |\n" for r in table)
        (self.output / "sweep.md").write_text(md)
        print(md)


def _fmt(value) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)
