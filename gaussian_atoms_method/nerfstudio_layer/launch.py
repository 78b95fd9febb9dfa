"""``gaussian-atoms train`` through nerfstudio's trainer, for what only it does (the viewer while
training, other loggers, a loaded config; :func:`gaussian_atoms_method.cli.train_command.engine_runs`
sends those here), with the same options, run directory and results as ``ns-train
gaussian-atoms``, started sooner: ``ns-train`` imports every method nerfstudio ships (and every
installed plugin) to build its command line; this builds it from this method's
:class:`~nerfstudio.engine.trainer.TrainerConfig` alone::

    gaussian-atoms train [trainer and model options] tilt-series --data DIR

One process on one device; multi-GPU and multi-machine runs go through ``ns-train``.

Also a short loop without the trainer for tests and stress cases (:func:`train_views`) and a
finished run's model loaded back (:func:`load_model`).
"""

from __future__ import annotations

import random
from pathlib import Path
from typing import Sequence

import torch

from gaussian_atoms_method.engine.errors import OptionError


def build_config(argv: list[str]):
    """Parse ``argv`` (the options ``ns-train gaussian-atoms`` takes after the method name)
    into a :class:`~nerfstudio.engine.trainer.TrainerConfig` based on this method's defaults."""
    import tyro

    from gaussian_atoms_method.nerfstudio_layer.config import gaussian_atoms_trainer_config

    tyro.extras.set_accent_color("bright_yellow")
    default = gaussian_atoms_trainer_config()
    default.vis = "tensorboard"  # no viewer left serving unless asked (--vis viewer); ns-train keeps nerfstudio's
    # As ns-train: booleans take a value (``--pipeline.model.cluster-merge False``), since
    # nerfstudio wraps its method configs in FlagConversionOff; sweeps pass flags that way.
    return tyro.cli(
        type(default),
        default=default,
        config=(tyro.conf.FlagConversionOff,),
        args=argv,
        prog="gaussian-atoms train",
        description=__doc__.split("\n\n")[0] + "\n\nOptions are those of `ns-train gaussian-atoms`.",
    )


def run(config) -> None:
    """Train with ``config`` in this process, as ``ns-train``'s single-device launch does."""
    import yaml

    if config.machine.num_devices * config.machine.num_machines != 1:
        raise OptionError(
            f"--machine.num-devices {config.machine.num_devices} / --machine.num-machines "
            f"{config.machine.num_machines}: gaussian-atoms train runs on one device; use "
            "`ns-train gaussian-atoms` for distributed training"
        )
    if config.load_config:
        config = yaml.load(config.load_config.read_text(), Loader=yaml.Loader)
    config.set_timestamp()
    config.check_or_exit()  # no dump of the configuration: it is in config.yml

    def console_of_our_own(config) -> None:  # after config.yml is saved
        if config.logging.profiler == "basic":  # nerfstudio's timing table would follow the results
            config.logging.profiler = "none"

    trainer = make_trainer(config, console_of_our_own)
    try:
        trainer.train()  # GaussianAtomsTrainer: its progress line; failures and Ctrl+C in one line
    finally:
        from nerfstudio.utils import profiler

        profiler.flush_profiler(config.logging)


def exit_process(status: int = 0) -> None:
    """:func:`gaussian_atoms_method.launch.process_exit.exit_process`, nerfstudio's TensorBoard writers
    closed first (nerfstudio leaves their files to the interpreter's shutdown)."""
    from nerfstudio.utils import writer

    from gaussian_atoms_method.launch.process_exit import exit_process as end

    for event_writer in writer.EVENT_WRITERS:
        tensorboard = getattr(event_writer, "tb_writer", None)
        if tensorboard is not None:
            tensorboard.close()
    end(status)


def make_trainer(config, after_saving=None):
    """Save ``config.yml``, seed every generator with ``config.machine.seed`` and build the
    trainer, set up for one process on one device (what ``ns-train`` does before training);
    ``after_saving(config)``, if given, changes what is not to be saved before the set-up."""
    import numpy as np
    import torch

    config.save_config()
    if after_saving is not None:
        after_saving(config)
    seed = config.machine.seed
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    return trainer


def train_views(model, cameras, targets: Sequence[torch.Tensor], steps: int, refine: bool = True):
    """Train ``model`` for ``steps`` steps, one view per step in turn.

    Parameters
    ----------
    model : GaussianAtomsModel
    cameras : nerfstudio Cameras, one per view
    targets : per view, the (H, W, 1) measured projection in normalised units
    steps : int
    refine : bool
        Run the densify / prune / merge callbacks as the trainer does.

    Returns
    -------
    The loss of the last step (a float).
    """
    from nerfstudio.engine.optimizers import Optimizers

    from gaussian_atoms_method.nerfstudio_layer.config import gaussian_atoms_trainer_config

    optimizers = Optimizers(gaussian_atoms_trainer_config().optimizers, model.get_param_groups())
    loss = float("nan")
    for step in range(steps):
        model.step_cb(optimizers, step)
        optimizers.zero_grad_all()
        v = step % len(targets)
        out = model.get_loss_dict(model.get_outputs(cameras[v : v + 1]), {"image": targets[v]})["main_loss"]
        out.backward()
        optimizers.optimizer_step_all()
        loss = float(out.detach())
        if refine:
            model.refine_after_step(step)
            model.merge_after_step(step)
    return loss


def load_model(config: Path):
    """The model of a finished run (its ``config.yml``), loaded as ``ns-viewer`` loads it."""
    from nerfstudio.utils.eval_utils import eval_setup

    _, pipeline, _, _ = eval_setup(config, test_mode="inference")
    return pipeline.model
