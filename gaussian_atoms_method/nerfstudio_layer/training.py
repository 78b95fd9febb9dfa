"""A minimal training loop: the model, its optimisers and its own refinement callbacks,
without nerfstudio's Trainer (no datamanager, viewer, checkpoints).  Used by the tests and the
stress cases; ``ns-train`` does the same steps in the same order."""

from __future__ import annotations

from typing import Sequence

import torch


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
