"""The ``gaussian-atoms`` method as nerfstudio sees it: trainer, pipeline and optimiser settings,
and the trainer that runs it.

Learning rates are in normalised units (the detector's longer side is 1); the means' rate
decays tenfold over the run so that atoms settle to pm precision.

The run, as ``ns-train gaussian-atoms`` and ``gaussian-atoms train`` launch it: bad input
stops in one line before anything is written, and a failure in training in one line.

nerfstudio's ``ns-train`` prints the whole config, writes ``config.yml`` into a new run
directory and only then builds the dataparser and the model, so a broken tilt series or a
wrong option used to end in a 30-line traceback with a half-made run directory left behind.
:class:`GaussianAtomsTrainerConfig` checks the input (the tilt series, its truth file and the
model options) in :meth:`~GaussianAtomsTrainerConfig.print_to_terminal`, the first thing both
launchers do once the options are parsed; :class:`GaussianAtomsTrainer` turns a training
failure (a non-finite loss, which names its step and cause) or Ctrl+C into one line.
"""

from __future__ import annotations

import dataclasses
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Type

import torch
from nerfstudio.configs.base_config import LocalWriterConfig, LoggingConfig, MachineConfig, ViewerConfig
from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanager, FullImageDatamanagerConfig
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
from nerfstudio.engine.trainer import Trainer, TrainerConfig
from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig
from nerfstudio.plugins.types import MethodSpecification

from dataparsers.errors import TiltSeriesError
from dataparsers.tilt_series_dataparser import TiltSeriesDataParserConfig, TiltSeriesDataset
from gaussian_atoms_method.atoms.atom_set import AtomFileError, read_atoms
from gaussian_atoms_method.engine.errors import OptionError
from gaussian_atoms_method.engine.optimisers import RATES, adam
from gaussian_atoms_method.engine.rendering import VIEW_KEY
from gaussian_atoms_method.engine.step_graph import detached
from gaussian_atoms_method.launch.ns_train import prepare
from gaussian_atoms_method.launch.process_exit import fail
from gaussian_atoms_method.nerfstudio_layer.model import GaussianAtomsModelConfig
from gaussian_atoms_method.nerfstudio_layer.options import GaussianAtomsOptions
from gaussian_atoms_method.physics.devices import default_device

INPUT_ERRORS = (TiltSeriesError, AtomFileError, OptionError)
"""Errors in what the user gave: reported in one line, exit status 2."""


def check_input(config: TrainerConfig):
    """Raise one of :data:`INPUT_ERRORS`, naming the file or option, for input that cannot
    train: the model options, the tilt series (read and validated as the dataparser will) and
    its truth file.  Returns the series read (None for another dataparser)."""
    from gaussian_atoms_method.engine.run import RunSettings, check_settings

    check_settings(RunSettings(device=config.machine.device_type, max_num_iterations=config.max_num_iterations))
    model = config.pipeline.model
    if isinstance(model, GaussianAtomsOptions):
        model.check()
    datamanager = config.pipeline.datamanager
    dataparser = datamanager.dataparser
    if isinstance(dataparser, TiltSeriesDataParserConfig):
        data = config.data or datamanager.data or dataparser.data
        series = dataparser.load(data)
        if series.truth_path is not None:
            read_atoms(series.truth_path)
        return series
    return None


@dataclass
class GaussianAtomsTrainerConfig(TrainerConfig):
    """nerfstudio's TrainerConfig for this method; builds :class:`GaussianAtomsTrainer`."""

    _target: Type = field(default_factory=lambda: GaussianAtomsTrainer)

    def __post_init__(self) -> None:
        # ns-train's ``--data`` alias, applied as the options are parsed (ns-train would log a
        # line for it before the input check could speak).
        if self.data is not None:
            self.pipeline.datamanager.data, self.data = self.data, None

    def set_experiment_name(self) -> None:
        """nerfstudio's rule, reading the data where this method names them (``tilt-series --data``,
        the dataparser's): ``ns-train`` and ``gaussian-atoms train`` put a run of the same data in
        the same place (:func:`~gaussian_atoms_method.engine.run_files.experiment_name_of`)."""
        from gaussian_atoms_method.engine.run_files import experiment_name_of

        data = self.pipeline.datamanager.data or getattr(self.pipeline.datamanager.dataparser, "data", None)
        if self.experiment_name is None and data is not None:
            self.experiment_name = experiment_name_of(data)
        super().set_experiment_name()

    def print_to_terminal(self) -> None:
        # ns-train calls this first, before saving config.yml: check the input here; the
        # configuration is the file nerfstudio says it saves, not a dump on the console.
        self.check_or_exit()

    def decide_registration(self, series) -> None:
        """With ``decide_registration``, set the model's ``refine_alignment`` and ``refine_gain``
        as the views of ``series`` a fit did not see say
        (:func:`~gaussian_atoms_method.engine.run.choose_registration`), before nerfstudio saves
        config.yml: the run's configuration records the choice."""
        from gaussian_atoms_method.engine.options import FitOptions
        from gaussian_atoms_method.engine.run import RunSettings, choose_registration

        model = self.pipeline.model
        if series is None or not getattr(model, "decide_registration", False):
            return
        steps, device = self.max_num_iterations, self.machine.device_type
        settings = RunSettings(device=device, max_num_iterations=steps, schedule_steps=steps, seed=self.machine.seed)
        # the fit's own options (the trial fits' config.yml records them, not splatfacto's)
        options = FitOptions(**{f.name: getattr(model, f.name) for f in dataclasses.fields(FitOptions)})
        for name, value in choose_registration(series, options, settings).items():
            setattr(model, name, value)
        model.decide_registration = False

    def check_or_exit(self) -> None:
        """:func:`check_input`, then :meth:`decide_registration` on the series it read (both
        launchers call this before config.yml is saved); a failure ends the process in one line
        (exit 2)."""
        try:
            self.decide_registration(check_input(self))
        except INPUT_ERRORS as exc:
            fail(f"gaussian-atoms: error: {exc}", 2)


class GaussianAtomsTrainer(Trainer):
    """nerfstudio's Trainer; a failure during training ends in one line naming its step and cause;
    on a GPU its steps are replays of a CUDA graph (:mod:`.step_graph`).  With ``psf held-out``
    it trains twice: a pass that reads the point-spread function, then the run with it held; after
    a second look (:mod:`gaussian_atoms_method.engine.second_look`) the run again from its places
    (:func:`start_again`)."""

    def train_iteration(self, step: int):
        # On a GPU a replay of the step captured as a CUDA graph where the model's step graph serves it (.step_graph).
        graph = getattr(self.pipeline.model, "step_graph", None)
        done = graph.train_iteration(TrainerSteps(self), step) if graph is not None else None
        # the loop holds them while the next step runs
        return done if done is not None else detached(*super().train_iteration(step))

    def train_passes(self) -> None:
        """nerfstudio's loop, and again while the fit starts again (:func:`start_again`).  A failure
        raises."""
        super().train()
        while start_again(self):
            if getattr(self, "progress", None) is not None:  # the restart made the callbacks anew
                follow(self.progress, self)
            super().train()

    def train(self) -> None:
        config = getattr(self, "config", None)
        own = getattr(self, "progress", None) is None and config is not None and not config.logging.local_writer.enable
        if own:  # ns-train: our progress line, not nerfstudio's table of steps (--logging.local-writer.enable)
            from gaussian_atoms_method.engine.progress import ProgressBar

            self.progress = ProgressBar(self.config.max_num_iterations)
            follow(self.progress, self)
        try:
            self.train_passes()
        except FloatingPointError as exc:  # the model names the step and the cause
            fail(str(exc), 1)
        except KeyboardInterrupt:
            # Ctrl+C, also how a viewer left open after training is closed.  Results are written
            # at the last step only, so an interrupted run leaves none half-written.
            fail("gaussian-atoms: interrupted", 130)
        finally:
            if own:
                self.progress.close()


def follow(bar, trainer) -> None:
    """Start ``bar`` (:class:`~gaussian_atoms_method.engine.progress.ProgressBar`) over and count
    ``trainer``'s steps after each (again for a second pass)."""
    bar.reset()
    trainer.callbacks.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], bar.count))


class TrainerSteps:
    """nerfstudio's trainer as the step graph's :class:`~gaussian_atoms_method.engine.step_graph.Steps`."""

    def __init__(self, trainer: Trainer) -> None:
        self.trainer, self.fit = trainer, trainer.pipeline.model

    def next_view(self, step: int):
        return self.trainer.pipeline.datamanager.next_train(step)

    def zero_grads(self) -> None:
        self.trainer.optimizers.zero_grad_some(list(self.trainer.optimizers.parameters))

    def optimiser_step(self, step: int) -> None:
        optimizers = self.trainer.optimizers
        optimizers.optimizer_scaler_step_some(self.trainer.grad_scaler, list(optimizers.parameters))
        optimizers.scheduler_step_all(step)

    def eager_reason(self) -> str:
        trainer = self.trainer
        accumulate = getattr(trainer, "gradient_accumulation_steps", {})
        if trainer.mixed_precision or trainer.config.log_gradients or any(n != 1 for n in accumulate.values()):
            return "mixed precision, gradient logging or gradient accumulation"
        return ""


def start_again(trainer) -> bool:
    """After a pass that reports no atoms (``psf held-out``'s reading pass, a second look): the
    fit starts again (:meth:`~gaussian_atoms_method.engine.fit.AtomFit.start_again`), with fresh
    optimisers and callbacks; False when the run is over.  nerfstudio's
    loop runs again from the step it started at (0, or a checkpoint's: the trainer's start is
    its own, not set here)."""
    model = trainer.pipeline.model
    if not hasattr(model, "start_again") or not model.start_again():
        return False
    trainer.optimizers = trainer.setup_optimizers()
    trainer.callbacks = trainer.pipeline.get_training_callbacks(
        TrainingCallbackAttributes(
            optimizers=trainer.optimizers, grad_scaler=trainer.grad_scaler, pipeline=trainer.pipeline, trainer=trainer
        )
    )
    return True


MAX_ITERATIONS = 3000

prepare(sys.argv)  # ns-train gaussian-atoms only: its start begun while nerfstudio loads (launch/ns_train.py)


@dataclass
class AdamConfig(AdamOptimizerConfig):
    """nerfstudio's Adam config building the engine's Adam
    (:func:`gaussian_atoms_method.engine.optimisers.adam`)."""

    def setup(self, params) -> torch.optim.Optimizer:
        return adam(params, lr=self.lr, eps=self.eps, weight_decay=self.weight_decay)


def nerfstudio_optimizers(max_iterations: int) -> dict:
    """The engine's rates (:data:`~gaussian_atoms_method.engine.optimisers.RATES`) as
    nerfstudio's optimizer and scheduler configs, the schedules over ``max_iterations``."""
    return {
        name: {
            "optimizer": AdamConfig(lr=rate.lr, eps=rate.eps),
            "scheduler": ExponentialDecaySchedulerConfig(lr_final=rate.lr_final, max_steps=max_iterations)
            if rate.lr_final is not None
            else None,
        }
        for name, rate in RATES.items()
    }


class TiltSeriesDatamanager(FullImageDatamanager[TiltSeriesDataset]):
    """nerfstudio's full-image datamanager serving float projections from memory.  Each view's
    camera is cut from the set once and kept: nerfstudio cuts and copies it at every step, a
    tenth of a large fit's step on a GPU.  So is its
    image on the device: a plain copy to the GPU at every step waited for the queued steps
    (``torch.cuda.set_sync_debug_mode``)."""

    def next_train(self, step: int):
        """The next training view's camera (its view index in ``metadata``:
        :func:`~gaussian_atoms_method.engine.rendering.view_of`) and its data, in nerfstudio's
        order (:meth:`FullImageDatamanager.next_train`)."""
        image_idx = self.train_unseen_cameras.pop(0)
        if len(self.train_unseen_cameras) == 0:
            self.train_unseen_cameras = self.sample_train_cameras()
        # a copy: the cache is not changed (reading it first loads it, and the cameras)
        data = dict(self.cached_train[image_idx])
        cameras, images = self.__dict__.setdefault("_view_cameras", {}), self.__dict__.setdefault("_view_images", {})
        if image_idx not in cameras:
            cameras[image_idx] = as_view(self.train_cameras[image_idx : image_idx + 1].to(self.device), image_idx)
            images[image_idx] = data["image"].to(self.device)
        data["image"] = images[image_idx]
        return cameras[image_idx], data


def as_view(camera, index: int):
    """``camera`` (one of nerfstudio's) marked as view ``index`` of the fit
    (:data:`~gaussian_atoms_method.engine.rendering.VIEW_KEY`), an int: read at every step
    without waiting for the GPU, where the dataparser's mark is a tensor moved there."""
    camera.metadata = {**(camera.metadata or {}), VIEW_KEY: int(index)}
    return camera


def gaussian_atoms_trainer_config(max_iterations: int = MAX_ITERATIONS) -> GaussianAtomsTrainerConfig:
    """The default configuration of ``ns-train gaussian-atoms``."""
    return GaussianAtomsTrainerConfig(
        method_name="gaussian-atoms",
        steps_per_eval_image=500,
        steps_per_eval_batch=0,
        steps_per_save=1000,
        steps_per_eval_all_images=100000,
        max_num_iterations=max_iterations,
        mixed_precision=False,
        machine=MachineConfig(device_type=default_device()),
        pipeline=VanillaPipelineConfig(
            datamanager=FullImageDatamanagerConfig(
                _target=TiltSeriesDatamanager,
                dataparser=TiltSeriesDataParserConfig(),
                # "gpu" means "on the training device"; "cpu" pins memory, which needs CUDA.
                cache_images="gpu",
                cache_images_type="float32",
            ),
            model=GaussianAtomsModelConfig(),
        ),
        optimizers=nerfstudio_optimizers(max_iterations),
        # a progress line of our own (GaussianAtomsTrainer.train), no table of steps or of timings
        logging=LoggingConfig(local_writer=LocalWriterConfig(enable=False), profiler="none"),
        # this machine only, unless --viewer.websocket-host says more
        viewer=ViewerConfig(num_rays_per_chunk=1 << 15, websocket_host="127.0.0.1"),
        vis="viewer",
    )


gaussian_atoms_method = MethodSpecification(
    config=gaussian_atoms_trainer_config(),
    description="Atomic electron tomography: one isotropic 3D Gaussian per atom, fitted to a tilt series.",
)


def trainer_config_of_run(
    place: dict,
    data: str,
    dataparser: dict,
    model: dict,
    max_num_iterations: int,
    schedule_steps: int,
    seed: int,
    device_type: str,
    vis: str,
) -> GaussianAtomsTrainerConfig:
    """The nerfstudio config of a run the engine trained (its ``config.yml`` calls this when
    loaded, :mod:`gaussian_atoms_method.engine.run_files`): the one ``ns-train gaussian-atoms``
    would have saved for the same settings."""
    config = gaussian_atoms_trainer_config(schedule_steps)
    config.max_num_iterations, config.vis = max_num_iterations, vis
    config.output_dir, config.experiment_name, config.timestamp = (
        Path(place["output_dir"]),
        place["experiment_name"],
        place["timestamp"],
    )
    config.machine.seed, config.machine.device_type = seed, device_type
    config.pipeline.datamanager.dataparser.data = Path(data)
    for target, values in ((config.pipeline.datamanager.dataparser, dataparser), (config.pipeline.model, model)):
        hints = {f.name: str(f.type) for f in dataclasses.fields(target)}
        for name, value in values.items():
            if isinstance(value, list):
                value = tuple(value)
            elif isinstance(value, str) and "Path" in hints.get(name, ""):
                value = Path(value)
            setattr(target, name, value)
    return config
