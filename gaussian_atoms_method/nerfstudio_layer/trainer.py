"""The run, as ``ns-train gaussian-atoms`` and ``gaussian-atoms train`` launch it: bad input
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

import sys
from dataclasses import dataclass, field
from typing import Type

from nerfstudio.engine.callbacks import TrainingCallbackAttributes
from nerfstudio.engine.trainer import Trainer, TrainerConfig

from dataparsers.errors import TiltSeriesError
from dataparsers.tilt_series_dataparser import TiltSeriesDataParserConfig
from gaussian_atoms_method.atoms.atom_set import AtomFileError, read_atoms
from gaussian_atoms_method.engine.console import CONSOLE
from gaussian_atoms_method.nerfstudio_layer.options import GaussianAtomsOptions, OptionError
from gaussian_atoms_method.nerfstudio_layer.step_graph import detached
from gaussian_atoms_method.start_ahead import end_now

INPUT_ERRORS = (TiltSeriesError, AtomFileError, OptionError)
"""Errors in what the user gave: reported in one line, exit status 2."""


def fail(message: str, status: int) -> None:
    """Print ``message`` as one line on stderr and exit with ``status`` (no traceback; at once
    where a start begun ahead is still running, :func:`~gaussian_atoms_method.start_ahead.end_now`)."""
    print(" ".join(str(message).split()), file=sys.stderr)
    end_now(status)
    raise SystemExit(status)


def check_input(config: TrainerConfig) -> None:
    """Raise one of :data:`INPUT_ERRORS`, naming the file or option, for input that cannot
    train: the model options, the tilt series (read and validated as the dataparser will) and
    its truth file."""
    check_device(config.machine.device_type)
    if not (isinstance(config.max_num_iterations, int) and config.max_num_iterations >= 1):
        raise OptionError(
            f"--max-num-iterations must be a whole number of steps, at least 1, got {config.max_num_iterations!r}"
        )
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


def check_device(device_type: str) -> None:
    """Raise :class:`OptionError` for a ``--machine.device-type`` this machine's torch cannot use."""
    from gaussian_atoms_method.physics.devices import usable

    if not usable(device_type):
        raise OptionError(
            f"--machine.device-type {device_type}: torch sees no such device here; use --machine.device-type cpu (the "
            f"default where no GPU is seen)"
        )


@dataclass
class GaussianAtomsTrainerConfig(TrainerConfig):
    """nerfstudio's TrainerConfig for this method; builds :class:`GaussianAtomsTrainer`."""

    _target: Type = field(default_factory=lambda: GaussianAtomsTrainer)

    def __post_init__(self) -> None:
        # ns-train's ``--data`` alias, applied as the options are parsed (ns-train would log a
        # line for it before the input check could speak).
        if self.data is not None:
            self.pipeline.datamanager.data, self.data = self.data, None

    def print_to_terminal(self) -> None:
        # ns-train calls this first, before saving config.yml: check the input here, then print
        # nerfstudio's dump of the configuration, as ns-train does for every method.
        self.check_or_exit()
        super().print_to_terminal()

    def check_or_exit(self) -> None:
        """:func:`check_input`, a failure ending the process in one line (exit 2)."""
        try:
            check_input(self)
        except INPUT_ERRORS as exc:
            fail(f"gaussian-atoms: error: {exc}", 2)


class GaussianAtomsTrainer(Trainer):
    """nerfstudio's Trainer; a failure during training ends in one line naming its step and cause;
    on a GPU its steps are replays of a CUDA graph (:mod:`.step_graph`).  With ``psf held-out``
    it trains twice: a pass that reads the point-spread function, then the run with it held
    (:func:`gaussian_atoms_method.engine.kernel_reading.restart_with_kernel_held`)."""

    def train_iteration(self, step: int):
        # On a GPU a replay of the step captured as a CUDA graph where the model's step graph serves it (.step_graph).
        graph = getattr(self.pipeline.model, "step_graph", None)
        done = graph.train_iteration(self, step) if graph is not None else None
        # the loop holds them while the next step runs
        return done if done is not None else detached(*super().train_iteration(step))

    def train(self) -> None:
        try:
            super().train()
            if restart_with_kernel_held(self):
                if getattr(self, "progress", None) is not None:  # the restart made the callbacks anew
                    self.progress.follow(self)
                super().train()
        except FloatingPointError as exc:  # the model names the step and the cause
            fail(str(exc), 1)
        except KeyboardInterrupt:
            # Ctrl+C, also how a viewer left open after training is closed.  Results are written
            # at the last step only, so an interrupted run leaves none half-written.
            fail("gaussian-atoms: interrupted", 130)


def restart_with_kernel_held(trainer) -> bool:
    """After the reading pass of ``psf held-out``: hold the kernel read (``psf fixed`` at the
    reading), start the atoms again from the start on every view, with fresh optimisers and
    callbacks, and return True; False when the trainer's model had no reading pass.

    Why start again: Gaussians formed on half the views without the kernel keep the satellites
    that explained the probe's tails (Ta film area 23, the reading pass's own atoms: 0.925 found,
    0.542 extra per model atom; the kernel held from the start: 0.946, 0.407)."""
    model = trainer.pipeline.model
    reading = getattr(model, "kernel_reading", None)
    if reading is None or not reading.first_pass:
        return False
    model.config.psf, model.config.psf_weights = (
        "fixed",
        tuple(float(w) for w in model.view_params["psf"].detach().cpu().tolist()),
    )
    CONSOLE.print(
        f"gaussian-atoms: the atoms start again on every view with the point-spread function held at "
        f"{', '.join(f'{w:.3f}' for w in model.config.psf_weights)} (1, 2, 4 Å)"
    )
    model.populate_modules()
    model.to(trainer.device)
    trainer.optimizers = trainer.setup_optimizers()
    trainer.callbacks = trainer.pipeline.get_training_callbacks(
        TrainingCallbackAttributes(
            optimizers=trainer.optimizers, grad_scaler=trainer.grad_scaler, pipeline=trainer.pipeline, trainer=trainer
        )
    )
    trainer._start_step = 0
    return True
