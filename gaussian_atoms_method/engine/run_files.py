"""A run's directory as nerfstudio lays it out, written by the engine without nerfstudio.

``OUTPUT/EXPERIMENT/gaussian-atoms/TIMESTAMP/`` holds ``config.yml``, ``dataparser_transforms.json``,
``nerfstudio_models/step-*.ckpt`` and the TensorBoard events, beside the results
(:mod:`.results`), so ``ns-viewer``, ``gaussian-atoms view``, ``export`` and
``check-precision`` read an engine run as they read an ``ns-train`` one:

* ``config.yml`` is a YAML call (``!!python/object/apply``) of
  :func:`gaussian_atoms_method.nerfstudio_layer.config.trainer_config_of_run` with the run's
  settings: loading it (nerfstudio loads it with PyYAML's full loader) builds the
  nerfstudio config ``ns-train`` would have saved, and only then imports nerfstudio;
* a checkpoint holds the fit's parameters under the pipeline's names (``_model.*``) and the
  optimisers' states.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field, fields, is_dataclass
from pathlib import Path

import numpy as np
import torch

TRAINER_CONFIG = "gaussian_atoms_method.nerfstudio_layer.config.trainer_config_of_run"
"""The function ``config.yml`` calls when it is loaded (a name in the file, not an import here)."""
METHOD_NAME = "gaussian-atoms"


def experiment_name_of(data) -> str:
    """A run's experiment name from its data, as nerfstudio's ``set_experiment_name`` makes it:
    the directory's name (a file's directory)."""
    data = Path(data)
    return str((data.parent if data.is_file() else data).stem)


@dataclass
class RunPlace:
    """Where a run's directory lies: ``output_dir / experiment_name / gaussian-atoms / timestamp``
    (nerfstudio's layout; ``experiment_name`` None: the data directory's name;
    ``timestamp`` ``{timestamp}``: the start's local time, ``%Y-%m-%d_%H%M%S``)."""

    output_dir: Path = Path("outputs")
    experiment_name: str | None = None
    timestamp: str = "{timestamp}"

    def resolved(self, data: Path) -> RunPlace:
        """The place with its experiment named and its time set, as nerfstudio's trainer sets
        them (``set_experiment_name``, ``set_timestamp``)."""
        name = self.experiment_name if self.experiment_name is not None else experiment_name_of(data)
        stamp = time.strftime("%Y-%m-%d_%H%M%S") if self.timestamp == "{timestamp}" else self.timestamp
        return RunPlace(Path(self.output_dir), name, stamp)

    @property
    def run_dir(self) -> Path:
        return Path(self.output_dir) / str(self.experiment_name) / METHOD_NAME / str(self.timestamp)


SEED = 42
"""The machine seed a run records in ``config.yml`` unless given one (``--machine.seed``):
``ns-train``'s own default, with which it seeds the global generators.  The fit draws from none
of them (its own generators are seeded by ``--pipeline.model.seed``), so the command, the API and
``ns-train gaussian-atoms`` give the same atoms."""


@dataclass
class RunRecord:
    """What ``config.yml`` records: enough to build the run's nerfstudio config again."""

    place: RunPlace
    data: Path
    dataparser: dict = field(default_factory=dict)
    """The tilt-series options given (:class:`dataparsers.tilt_series_options.TiltSeriesOptions`)."""
    model: dict = field(default_factory=dict)
    """The fit's options (:class:`~.options.FitOptions`), every one."""
    max_num_iterations: int = 3000
    schedule_steps: int = 3000
    seed: int = SEED
    device_type: str = "cpu"
    vis: str = "tensorboard"


def plain(value):
    """``value`` in YAML's plain types (paths as strings, tuples as lists, numpy's scalars as
    Python's: an option given as ``np.float64`` from an array is a number all the same)."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, (tuple, list)):
        return [plain(v) for v in value]
    if isinstance(value, dict):
        return {k: plain(v) for k, v in value.items()}
    if is_dataclass(value):
        return plain(asdict(value))
    return value


def options_dict(options) -> dict:
    """A dataclass of options as a plain dict (its public fields)."""
    return {f.name: plain(getattr(options, f.name)) for f in fields(options) if not f.name.startswith("_")}


def write_config(run_dir: Path, record: RunRecord) -> Path:
    """``run_dir/config.yml``: the call of :data:`TRAINER_CONFIG` with ``record``."""
    import yaml

    text = yaml.safe_dump({"kwds": plain(asdict(record))}, sort_keys=False)
    path = Path(run_dir) / "config.yml"
    path.write_text(f"!!python/object/apply:{TRAINER_CONFIG}\n{text}")
    return path


def write_transforms(run_dir: Path) -> None:
    """``dataparser_transforms.json``: the identity, as the tilt-series dataparser applies none."""
    identity = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]]
    (Path(run_dir) / "dataparser_transforms.json").write_text(
        json.dumps({"transform": identity, "scale": 1.0}, indent=4)
    )


def write_checkpoint(run_dir: Path, step: int, fit: torch.nn.Module, optimisers) -> Path:
    """``nerfstudio_models/step-<step>.ckpt`` as nerfstudio's trainer writes it (the parameters
    as its pipeline names them; nerfstudio's model adds an empty device marker)."""
    folder = Path(run_dir) / "nerfstudio_models"
    folder.mkdir(parents=True, exist_ok=True)
    pipeline = {"_model." + k: v for k, v in fit.state_dict().items()}
    pipeline.setdefault("_model.device_indicator_param", torch.empty(0))
    path = folder / f"step-{step:09d}.ckpt"
    torch.save({"step": step, "pipeline": pipeline, **optimisers.state_dict(), "scalers": {}}, path)
    for old in folder.glob("step-*.ckpt"):  # nerfstudio keeps the latest only (save_only_latest_checkpoint)
        if old != path:
            old.unlink()
    return path


class Scalars:
    """The run's TensorBoard scalars under nerfstudio's names and at its steps: every step the
    decaying rates (``learning_rate/*``), every ``every`` steps the loss and the step's metrics
    (``Train Loss``, ``Train Loss Dict/*``, ``Train Metrics Dict/*``, ``GPU Memory (MB)``).

    The loss and metrics stay on the device until ``flush_every`` of them are queued, then come
    to the host in one copy: reading each at its step would make the host wait for the GPU's
    queue every ``every`` steps."""

    def __init__(self, run_dir: Path, every: int = 10, flush_every: int = 10) -> None:
        from gaussian_atoms_method.engine.event_file import ScalarEvents

        self.writer, self.every, self.flush_every = ScalarEvents(run_dir), every, flush_every
        self.queued: list[tuple[int, dict, float]] = []

    def write(self, step: int, loss: torch.Tensor, losses: dict, metrics: dict, optimisers) -> None:
        for name, scheduler in optimisers.schedulers.items():
            self.writer.add_scalar(f"learning_rate/{name}", scheduler.get_last_lr()[0], step)
        if not self.every or step % self.every:
            return
        values = {"Train Loss": loss}
        values |= {f"Train Loss Dict/{k}": v for k, v in losses.items()}
        values |= {f"Train Metrics Dict/{k}": v for k, v in metrics.items()}
        self.queued.append((step, values, torch.cuda.max_memory_allocated() / 1024**2))
        if len(self.queued) >= self.flush_every:
            self.flush()

    def flush(self) -> None:
        """Write the queued scalars (one copy from the device) and the rates to the file."""
        if self.queued:
            tensors = [
                torch.as_tensor(v, dtype=torch.float64).reshape(())
                for _, values, _ in self.queued
                for v in values.values()
            ]
            host = iter(torch.stack([t.to(tensors[0].device) for t in tensors]).cpu().tolist())
            for step, values, memory in self.queued:
                for name in values:
                    self.writer.add_scalar(name, next(host), step)
                self.writer.add_scalar("GPU Memory (MB)", memory, step)
            self.queued = []
        self.writer.flush()

    def close(self) -> None:
        self.flush()
        self.writer.close()
