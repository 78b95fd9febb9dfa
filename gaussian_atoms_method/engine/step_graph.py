"""A training step's GPU work captured once as a CUDA graph and replayed, step after step.

At 20,000 atoms and more a step on an H100 is bound by the host, not the GPU: about 300 small
operations, each dispatched from Python (6-7 ms a step), for about 2 ms of the GPU's own work
(docs/performance.md, "Training steps that do not wait for the GPU").  Captured as a graph, the
projection of the step's views, the floors, the loss, the floors' closed-form solve and the
backward pass are one launch; what stays with the host is nerfstudio's choice of view, two
copies into the graph's inputs (the views' device index and the measured image), Adam's fused
kernels with their schedule and the callbacks (the clamp, the iterates' mean, the density
control).  The loop that drives it (the engine's, :mod:`.training`, or nerfstudio's trainer)
hands it a :class:`Steps`: where the views, the gradients and the optimisers are.

A graph reads fixed addresses, so it is captured again whenever a tensor it reads moved or its
shape changed: a refine or a merge replaced the parameters, the coarse phase ended, the views'
floors became shared or separate.  Before each capture one step runs eagerly with the new
set-up, which makes the state a graph must not allocate (Adam's moments, the model's caches).
Steps the graph does not serve run eagerly, as nerfstudio's: off a GPU, with
``--pipeline.model.cuda-graphs False``, and where a step's work depends on the host each step
(per-view parameters, a kernel read on held-out views or held fixed, another projector, mixed
precision, gradient accumulation).  Eager and captured steps run the same code
(``tests/test_cuda.py`` compares their parameters after a run).
"""

from __future__ import annotations

import functools
from typing import Protocol

import torch

from gaussian_atoms_method.engine.console import CONSOLE
from gaussian_atoms_method.engine.rendering import projector_name
from gaussian_atoms_method.engine.step_views import step_views


class Steps(Protocol):
    """What a training loop gives the graph: its fit, the next view, and its optimisers."""

    fit: torch.nn.Module

    def next_view(self, step: int) -> tuple:
        """The step's camera and its batch (``{"image": (H, W, 1)}``), in the loop's order."""

    def zero_grads(self) -> None:
        """Every gradient set to None."""

    def optimiser_step(self, step: int) -> None:
        """Adam's step for every group with a gradient, then the schedules'."""

    def eager_reason(self) -> str:
        """Why the loop's own settings need eager steps ('' where they do not)."""


class StepGraph:
    """The trainer's captured step (:meth:`train_iteration`); the model holds one."""

    def __init__(self) -> None:
        self.index_in_use: torch.Tensor | None = (
            None  # the step's views, read by rendering.step_index while set (a capture)
        )
        self._graph = None
        self._key = None  # the set-up the graph was captured for (_key_of)
        self._warm = None  # the set-up of the last eager step
        self._inputs: tuple[torch.Tensor, torch.Tensor] | None = None  # the views' index and the measured image
        self._grads: list = []
        self._outputs = None
        self._counts = None  # the finiteness counts the graph computes (rendering.FiniteWatch)
        self._off: str | None = None  # why steps run eagerly for the whole run, once found
        self.replays, self.captures = 0, 0  # steps served and graphs captured, over the run

    def train_iteration(self, steps: Steps, step: int):
        """Run the loop's step ``step`` as a replay of the captured graph (capturing it first
        where the set-up changed) and return (loss, loss_dict, metrics_dict); None where the
        step should run eagerly (the loop's own step)."""
        model = steps.fit
        if self._off is None:
            self._off = why_eager(model, steps.eager_reason())
        key = None if self._off else self._key_of(model, step)
        if key != self._key:
            self.drop()
        if key is None or (key != self._key and key != self._warm):
            self._warm = key  # this step eagerly: the next one with this set-up is captured
            return None
        camera, batch = steps.next_view(step)
        dev, dt = model.means.device, model.means.dtype
        view = model.view_geometry.read(camera, camera.camera_to_worlds[0].to(dt), key[-3], dev, dt)[3]
        views = torch.tensor(step_views(model, view), dtype=torch.long).pin_memory()
        if self._graph is None:
            self._inputs = (torch.empty(len(views), dtype=torch.long, device=dev), torch.empty_like(batch["image"]))
        index, image = self._inputs
        index.copy_(views, non_blocking=True)
        image.copy_(batch["image"])
        if self._graph is None and not self._capture(steps, model, camera, key):
            return self._eager(steps, model, camera, step)  # the views drawn for it
        self._graph.replay()
        self.replays += 1
        for param, grad in self._grads:  # nerfstudio's zero_grad set them to None; the graph writes these
            param.grad = grad
        loss, losses, metrics = self._outputs
        if self._counts is not None:
            model.finite_watch.queue(*self._counts, step)
        steps.optimiser_step(step)
        return loss, losses, metrics

    def drop(self) -> None:
        """Forget the captured graph (its memory goes back to the allocator)."""
        self._graph, self._key, self._grads, self._outputs, self._inputs, self._counts = (
            None,
            None,
            [],
            None,
            None,
            None,
        )

    @staticmethod
    def _key_of(model, step: int) -> tuple:
        """What a graph fixes: every parameter's address and shape, the coarse phase, whether
        the floors are shared, the views a step."""
        params = tuple((p.data_ptr(), tuple(p.shape)) for p in model.parameters())
        return params + (step < model.config.coarse_steps, model.floors.shared, model.views_per_step)

    def _capture(self, steps: Steps, model, camera, key) -> bool:
        """Capture the step's tensor work (:func:`step_losses` and the backward pass) on the
        inputs; False (and steps eager from now on, with one line saying why) if it cannot be."""
        model.prepared.quiet()  # no other thread may launch work during a capture
        steps.zero_grads()  # the graph's backward writes the gradients afresh
        graph, index, image = torch.cuda.CUDAGraph(), *self._inputs
        self.index_in_use, model.finite_watch.captured = index, None
        try:
            with torch.cuda.graph(graph):
                loss, losses, metrics = step_losses(model, camera, {"image": image})
                loss.backward()
        except RuntimeError as exc:
            self._off = f"a training step could not be captured as a CUDA graph ({str(exc).splitlines()[0]})"
            CONSOLE.print(f"gaussian-atoms: {self._off}: steps run one operation at a time")
            self._graph, self._key = None, None
            return False
        finally:
            self.index_in_use = None
        self._graph, self._key, self._outputs = graph, key, detached(loss, losses, metrics)
        self.captures += 1
        self._grads = [(p, p.grad) for p in model.parameters() if p.grad is not None]
        self._counts = model.finite_watch.captured
        return True

    def _eager(self, steps: Steps, model, camera, step: int):
        """The step on ``camera`` and the views and image already in the inputs, run eagerly."""
        steps.zero_grads()
        self.index_in_use, image = self._inputs
        try:
            loss, losses, metrics = step_losses(model, camera, {"image": image})
            loss.backward()
        finally:
            self.index_in_use, self._inputs = None, None
        steps.optimiser_step(step)
        return detached(loss, losses, metrics)


def detached(loss: torch.Tensor, losses: dict, metrics: dict) -> tuple:
    """A step's (loss, loss_dict, metrics_dict) without their autograd graph.  nerfstudio's loop
    holds a step's results while the next step runs; kept attached, they keep the parameters'
    gradient accumulators of that step alive, and a capture on the graph's stream then fails
    on the accumulators' stream (CUDA's "operation failed due to a previous error during capture")."""

    def plain(value):
        return value.detach() if isinstance(value, torch.Tensor) else value

    return plain(loss), {k: plain(v) for k, v in losses.items()}, {k: plain(v) for k, v in metrics.items()}


def step_losses(model, camera, batch: dict) -> tuple:
    """(loss, loss_dict, metrics_dict) of the model's step on ``camera`` and ``batch``, as
    nerfstudio's pipeline computes them (:meth:`VanillaPipeline.get_train_loss_dict`)."""
    outputs = model(camera)
    metrics = model.get_metrics_dict(outputs, batch)
    losses = model.get_loss_dict(outputs, batch, metrics)
    return functools.reduce(torch.add, losses.values()), losses, metrics


def why_eager(model, loop_reason: str = "") -> str:
    """Why the steps of ``model`` cannot be served by a graph ('' where they can);
    ``loop_reason``: the loop's own (:meth:`Steps.eager_reason`)."""
    cfg = model.config
    if not cfg.cuda_graphs:
        return "--pipeline.model.cuda-graphs False"
    if not model.means.is_cuda:
        return "not on a CUDA GPU"
    if not model.indexed_views or cfg.psf in ("held-out", "fixed"):
        return "per-view parameters, or a kernel not learned with the atoms"
    if projector_name(cfg.projector, model.means.device) != "dense":
        return "a projector other than the dense one"
    return loop_reason
