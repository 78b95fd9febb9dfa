"""The training loop: the fit's steps over its views, in plain torch.

Each step, in the order nerfstudio's trainer runs them for ``ns-train gaussian-atoms`` (so that
both give the same atoms): the fit's step callback, the step itself (the views' projections,
the loss, its gradients, Adam and the schedules; on a GPU a replay of the step captured as a
CUDA graph, :mod:`.step_graph`), then the refine, the merge, the results at the last step, the
stop, the snapshot and the progress bar; a checkpoint every ``save_every`` steps and at the end.
The views come in the order of nerfstudio's full-image datamanager: each pass over them a
shuffle by its own generator (seed 42).  With ``psf held-out`` a reading pass comes first, then
the run again with the kernel held; after a second look the run again from its places
(:meth:`.fit.AtomFit.start_again`).
"""

from __future__ import annotations

import random
from dataclasses import dataclass, replace
from pathlib import Path

import torch

from gaussian_atoms_method.engine.optimisers import Optimisers
from gaussian_atoms_method.engine.rendering import VIEW_KEY
from gaussian_atoms_method.engine.run_files import Scalars, write_checkpoint
from gaussian_atoms_method.engine.step_graph import detached, step_losses
from gaussian_atoms_method.engine.views import OrthographicViews

VIEW_ORDER_SEED = 42
"""The views' shuffle's seed (nerfstudio's ``train_cameras_sampling_seed``)."""


class ViewOrder:
    """The training views' order: every pass a fresh shuffle of the V views."""

    def __init__(self, n_views: int, seed: int = VIEW_ORDER_SEED) -> None:
        self.n, self.rng = n_views, random.Random(seed)
        self.unseen = self._shuffled()

    def _shuffled(self) -> list[int]:
        indices = list(range(self.n))
        self.rng.shuffle(indices)
        return indices

    def next(self) -> int:
        index = self.unseen.pop(0)
        if not self.unseen:
            self.unseen = self._shuffled()
        return index


@dataclass
class LoopSettings:
    """``max_steps``: the step limit; ``schedule_steps``: the decaying rates' steps;
    ``save_every``: steps between checkpoints (0: at the end only); ``checkpoints``: False for
    none (a run whose directory is not kept)."""

    max_steps: int = 3000
    schedule_steps: int = 3000
    save_every: int = 1000
    checkpoints: bool = True


class FitLoop:
    """The fit's views, measured images, view order and optimisers: the step graph's
    :class:`~.step_graph.Steps`.

    Parameters
    ----------
    fit : AtomFit, on its device
    views : the V views (:class:`~.views.OrthographicViews`)
    images : (V, H, W) measured projections in normalised units
    """

    def __init__(self, fit, views: OrthographicViews, images: torch.Tensor, schedule_steps: int) -> None:
        dev = fit.means.device
        self.fit, self.schedule_steps = fit, schedule_steps
        self.cameras = [replace(views[i].to(dev), metadata={VIEW_KEY: i}) for i in range(len(views))]
        self.images = [images[i][..., None].to(dev, torch.float32) for i in range(len(views))]
        self.order = ViewOrder(len(views))
        self.optimisers = Optimisers(fit.get_param_groups(), schedule_steps)

    def fresh_optimisers(self) -> None:
        """New optimisers for the fit's parameters as they now are (a restart)."""
        self.optimisers = Optimisers(self.fit.get_param_groups(), self.schedule_steps)

    def next_view(self, step: int):
        index = self.order.next()
        return self.cameras[index], {"image_idx": index, "image": self.images[index]}

    def zero_grads(self) -> None:
        self.optimisers.zero_grad_all()

    def optimiser_step(self, step: int) -> None:
        self.optimisers.step()

    def eager_reason(self) -> str:
        return ""

    def train_step(self, step: int):
        """One step: (loss, loss_dict, metrics_dict), detached."""
        done = self.fit.step_graph.train_iteration(self, step)
        if done is not None:
            return done
        self.zero_grads()
        camera, batch = self.next_view(step)
        loss, losses, metrics = step_losses(self.fit, camera, batch)
        loss.backward()
        self.optimiser_step(step)
        return detached(loss, losses, metrics)


def run_pass(loop: FitLoop, run_dir: Path, settings: LoopSettings, progress=None, scalars: Scalars | None = None):
    """Train until the step limit or the stop; the checkpoints as nerfstudio's trainer writes
    them (the last one numbered by the step after the stop, as its loop numbers it)."""
    fit, last = loop.fit, settings.max_steps - 1
    snapshots = Path(run_dir) / "snapshots" if fit.config.snapshot_every > 0 else None
    step, stop = 0, False
    for step in range(settings.max_steps):
        if stop:
            break
        fit.train()
        fit.step_cb(loop.optimisers, step)
        loss, losses, metrics = loop.train_step(step)
        fit.refine_after_step(step)
        fit.merge_after_step(step)
        fit.write_results_at(last, run_dir, step)
        stop = fit.should_stop(step, last, run_dir, progress)
        if snapshots is not None:
            fit.snapshot_after_step(snapshots, step)
        if progress is not None:
            progress.count(step)
        if scalars is not None:
            scalars.write(step, loss, losses, metrics, loop.optimisers)
        if settings.checkpoints and settings.save_every and step and step % settings.save_every == 0:
            write_checkpoint(run_dir, step, fit, loop.optimisers)
    if settings.checkpoints:
        write_checkpoint(run_dir, step, fit, loop.optimisers)


def train(loop: FitLoop, run_dir: Path, settings: LoopSettings, progress=None, scalars: Scalars | None = None) -> None:
    """The run: :func:`run_pass`, and again while the fit starts again (:meth:`.fit.AtomFit.start_again`:
    after ``psf held-out``'s reading pass, or a second look)."""
    run_pass(loop, run_dir, settings, progress, scalars)
    while loop.fit.start_again():
        loop.fresh_optimisers()
        if progress is not None:
            progress.reset()
        run_pass(loop, run_dir, settings, progress, scalars)
