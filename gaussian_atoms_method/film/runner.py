"""Each sub-area's fit as a Ray task: local by default, a cluster with an address; resumable,
retried once, a failure reported by name while the others finish.

A sub-area's fit is :func:`fit_subarea` (the engine's run, :mod:`gaussian_atoms_method.engine.run`,
on the sub-area's tilt series).  It writes ``done.json`` in its run directory last, with the
settings it was fitted with, so a run stopped midway starts again at the sub-areas without one
(or fitted with other settings).  On a machine with GPUs each task
takes one; otherwise a task takes :func:`cores_per_task` cores and torch uses that many threads.
"""

from __future__ import annotations

import json
from pathlib import Path

from gaussian_atoms_method.film.subareas import SubArea

DONE = "done.json"


def place_of(runs_dir: Path | str, name: str):
    """The run place of sub-area ``name`` under ``runs_dir`` (its ``done.json`` in its run directory)."""
    from gaussian_atoms_method.engine.run_files import RunPlace

    return RunPlace(Path(runs_dir), name, "run")


def fit_subarea(
    subarea: dict, runs_dir: str, options: dict, device: str, max_steps: int, threads: int, species: str | None = None
) -> dict:
    """Fit one sub-area (``subarea``: :meth:`SubArea.to_json`) unless its ``done.json`` exists,
    with the film's ``species`` (its hard core) where given, else its series' own; return that
    record: the name, the atoms file, the hard core its run read, its steps and whether it
    converged before the step limit, and what the task cost (:func:`task_costs`)."""
    import time

    import torch

    from dataparsers.tilt_series_format import load_tilt_series
    from gaussian_atoms_method.engine.options import FitOptions
    from gaussian_atoms_method.engine.run import RunSettings, fit_tilt_series

    sub = SubArea.from_json(subarea)
    place = place_of(runs_dir, sub.name)
    done = place.run_dir / DONE
    asked = fit_settings(options, max_steps, species)
    record = finished(done, asked)
    if record is not None:
        return record
    if device == "cpu" and threads > 0:
        torch.set_num_threads(threads)
    if device == "cuda":
        torch.cuda.reset_peak_memory_stats()
    started = time.perf_counter()
    series = load_tilt_series(sub.data, species=species or None)
    settings = RunSettings(place, device, max_steps, progress=False, tensorboard=False, checkpoints=False)
    run = fit_tilt_series(series, FitOptions(**options), settings, sub.data)
    run_dir = run.run_dir
    structure = json.loads((run_dir / "structure.json").read_text())
    record = {
        "name": sub.name,
        "atoms": str(run_dir / "atoms.xyz"),
        "hard_core_A": structure.get("hard_core_A"),
        "steps": getattr(run.report, "steps", None),
        "converged": getattr(run.report, "converged", None),
        **task_costs(time.perf_counter() - started, device),
        "settings": asked,
    }
    tmp = done.with_suffix(".tmp")
    tmp.write_text(json.dumps(record) + "\n")
    tmp.replace(done)
    return record


def fit_settings(options: dict, max_steps: int, species: str | None) -> dict:
    """What decides a sub-area's atoms, as ``done.json`` records it: the fit's options, its step
    limit and the species (the device only changes the sums' rounding)."""
    return json.loads(json.dumps({"options": options, "max_steps": max_steps, "species": species or ""}))


def finished(done: Path, settings: dict) -> dict | None:
    """The record in ``done`` where it exists and was fitted with ``settings`` (:func:`fit_settings`);
    None otherwise: a sub-area finished with other settings, or before they were recorded, is
    fitted again rather than joined with the others as if it were theirs."""
    if not done.is_file():
        return None
    record = json.loads(done.read_text())
    return record if record.get("settings") == settings else None


def task_costs(seconds: float, device: str) -> dict:
    """What a sub-area's task cost: ``fit_s`` (reading the series to the written atoms),
    ``peak_gpu_GB`` (torch's largest allocation on the GPU during the fit; None off a GPU) and
    ``worker_rss_GB`` (the largest resident memory of the worker process so far: a Ray worker
    runs several tasks, so an upper bound for this one's)."""
    import resource

    import torch

    rss_kB = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # kilobytes on Linux
    return {
        "fit_s": round(seconds, 2),
        "peak_gpu_GB": round(torch.cuda.max_memory_allocated() / 1e9, 3) if device == "cuda" else None,
        "worker_rss_GB": round(rss_kB * 1024 / 1e9, 3),
    }


CONNECT_TIMEOUT_S = 5.0
"""How long :func:`check_address` waits for a cluster's head to accept a connection: a head on
the same network answers in milliseconds; Ray's own client keeps retrying for minutes."""


def check_address(address: str | None, timeout_s: float = CONNECT_TIMEOUT_S) -> None:
    """A ValueError naming ``address`` (``HOST:PORT`` or ``ray://HOST:PORT``; None or ``auto``:
    nothing to check) where it is malformed or nothing accepts a connection there, so a wrong
    address stops at once instead of leaving Ray retrying."""
    import socket

    if address is None or address == "auto":
        return
    host, _, port = address.split("://", 1)[-1].rpartition(":")
    if not host or not port.isdigit():
        raise ValueError(f"address {address!r}: expected HOST:PORT or ray://HOST:PORT")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s):
            pass
    except OSError as exc:
        raise ValueError(f"address {address}: no Ray cluster answers there ({exc.strerror or exc})") from None


def cluster_device(device: str, cluster_gpus: float, address: str | None) -> str:
    """The tasks' device on a Ray cluster with ``cluster_gpus`` GPUs: ``auto`` is ``cuda`` where it
    has any, else ``cpu``; ``cuda`` on a cluster without one is a ValueError naming it (its tasks
    would wait for a GPU forever)."""
    if device == "auto":
        return "cuda" if cluster_gpus > 0 else "cpu"
    if device == "cuda" and cluster_gpus <= 0:
        where = f"the Ray cluster at {address}" if address else "this machine's Ray cluster"
        raise ValueError(f"device cuda: {where} has no GPU; use cpu or auto")
    return device


def cores_per_task(n_tasks: int) -> int:
    """Cores for one CPU task: this machine's (at most the ``OMP_NUM_THREADS`` the environment
    sets, :func:`~gaussian_atoms_method.physics.devices.threads_given`) shared among at most
    ``n_tasks`` tasks, at least 2 each (torch's matrix products and the projector's tiles use two
    threads well; one task a core would leave each at half speed)."""
    from gaussian_atoms_method.physics.devices import threads_given

    cores = threads_given()
    if cores < 2:
        return 1
    return max(2, cores // max(1, min(n_tasks, cores // 2)))


def run_subareas(
    subareas: list[SubArea],
    runs_dir: Path,
    options: dict,
    device: str,
    max_steps: int,
    address: str | None = None,
    progress: bool = True,
    tasks_per_gpu: int = 1,
    species: str | None = None,
) -> tuple[dict[str, dict], dict[str, str]]:
    """Fit every sub-area as a Ray task; ``({name: record}, {name: why it failed})``.

    Sub-areas already done with the same settings are read back, not run (:func:`finished`); a
    failed task is retried once.  Each fit uses ``species`` where given (:func:`fit_subarea`).  On
    GPUs, ``tasks_per_gpu`` tasks share each GPU (a sub-area's fit is bound by its kernel
    launches, not the GPU's arithmetic, and holds a small part of its memory: :func:`task_costs`)."""
    try:
        import ray
    except ImportError as exc:
        raise RuntimeError("the film's sub-areas run on Ray: pip install 'gaussian-atoms[ray]'") from exc
    from tqdm.auto import tqdm

    records: dict[str, dict] = {}
    todo = []
    asked = fit_settings(options, max_steps, species)
    for sub in subareas:
        record = finished(place_of(runs_dir, sub.name).run_dir / DONE, asked)
        if record is not None:
            records[sub.name] = record
        else:
            todo.append(sub)
    failures: dict[str, str] = {}
    bar = tqdm(total=len(subareas), initial=len(records), desc="sub-areas", unit="area", disable=not progress)
    if todo:
        if not ray.is_initialized():
            ray.init(address=address, include_dashboard=False, log_to_driver=False, configure_logging=False)
        device = cluster_device(device, ray.cluster_resources().get("GPU", 0), address)
        gpu = device == "cuda"
        threads = 0 if gpu else cores_per_task(len(todo))
        resources = {"num_gpus": 1 / tasks_per_gpu} if gpu else {"num_cpus": threads}
        task = ray.remote(max_retries=1, retry_exceptions=True, **resources)(fit_subarea)
        pending = {
            task.remote(sub.to_json(), str(runs_dir), options, device, max_steps, threads, species): sub.name
            for sub in todo
        }
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            name = pending.pop(ready[0])
            try:
                records[name] = ray.get(ready[0])
            except Exception as exc:  # a task failed twice: say which, keep the others
                cause = getattr(exc, "cause", None) or exc
                failures[name] = " ".join(str(cause).split())[:300]
            bar.update(1)
    bar.close()
    return records, failures
