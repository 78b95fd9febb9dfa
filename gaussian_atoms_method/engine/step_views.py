"""The views of a training step: which views a step fits (one, or several in one projector call
where the projector's measured memory and time say it pays, ``views-per-step auto``), how they
are indexed on the device, and the checks that they can share a call."""

from __future__ import annotations

import torch

from gaussian_atoms_method.engine.console import CONSOLE
from gaussian_atoms_method.engine.errors import OptionError
from gaussian_atoms_method.engine.rendering import binned_views, index_on, projector_for, projector_name


def check_view_batches(views_per_step: int, projections, view_c2w: torch.Tensor) -> torch.Tensor:
    """The (V, H, W) measured projections the extra views of a step are fitted to (empty for
    one view per step), after checking the views can share one projector call (the options
    themselves are checked by :meth:`gaussian_atoms_method.nerfstudio_layer.options.GaussianAtomsOptions.check`);
    OptionError
    naming the option otherwise."""
    if views_per_step <= 1:
        return torch.zeros(0, 1, 1)
    if projections is None or view_c2w.shape[0] < 2:
        raise OptionError(
            "--pipeline.model.views-per-step > 1 needs a tilt series from the tilt-series dataparser (its projections "
            "and view poses)"
        )
    if not on_beam_axes(view_c2w):
        raise OptionError(
            "--pipeline.model.views-per-step > 1 needs every camera on its beam axis through the tilt centre"
        )
    return torch.as_tensor(projections, dtype=torch.float32)


def on_beam_axes(view_c2w: torch.Tensor) -> bool:
    """Whether every camera of the (V, 3, 4) poses sits on its beam axis through the tilt centre
    (true of the dataparser's): then one call projects the same means for every view, with no
    camera offset (:func:`step_index`)."""
    if view_c2w.shape[0] == 0:
        return False
    off_axis = (
        torch.stack([(view_c2w[:, :, 3] * view_c2w[:, :, 0]).sum(-1), (view_c2w[:, :, 3] * view_c2w[:, :, 1]).sum(-1)])
        .abs()
        .max()
    )
    return float(off_axis) <= 1e-5


def step_index(model, view: int, device: torch.device) -> torch.Tensor:
    """(V,) on ``device``: the training step's views, ``view`` and ``views_per_step - 1`` others
    drawn at random (none for one view a step); one index the projection, the floors, the
    measured views and the floors' solve all read.  While a step is captured as a CUDA graph,
    the graph's own index, which each replay refills (:mod:`gaussian_atoms_method.engine.step_graph`)."""
    in_use = model.step_graph.index_in_use
    return in_use if in_use is not None else index_on(step_views(model, view), device)


def step_views(model, view: int) -> list[int]:
    """The training step's views (host indices): ``view`` and the others
    (:meth:`.kernel_reading.HeldOutKernel.other_views`, drawn from the model's generator)."""
    if model.views_per_step <= 1:
        return [view]
    return [view, *model.kernel_reading.other_views(view, model.views_per_step, model.generator, model.step).tolist()]


def view_batches(cfg, projections, view_c2w: torch.Tensor) -> tuple[torch.Tensor, int | None]:
    """The measured projections a step's extra views are fitted to (:func:`check_view_batches`)
    and the views per step: the option's number, None for ``auto`` (resolved at the first
    training step, :func:`first_step_views`), 1 for ``auto`` with per-view parameters
    (refine-alignment, refine-tilts, anisotropic Gaussians) or without a tilt series' cameras."""
    views = 1 if cfg.views_per_step == "auto" and cfg.per_view_options() else cfg.views_per_step
    try:
        return check_view_batches(MAX_VIEWS_PER_STEP if views == "auto" else views, projections, view_c2w), (
            None if views == "auto" else views
        )
    except OptionError:
        if views != "auto":
            raise
        return torch.zeros(0, 1, 1), 1


def first_step_views(model) -> int:
    """``auto``'s views per step for ``model`` at its first training step: its Gaussians,
    detector and projector on its device (:func:`auto_views_per_step`); printed."""
    _, h, w = model.train_projections.shape
    dev, dt = model.means.device, model.means.dtype
    rows, cols = (
        torch.arange(h, device=dev, dtype=dt) - 0.5 * (h - 1),
        torch.arange(w, device=dev, dtype=dt) - 0.5 * (w - 1),
    )
    views = auto_views_per_step(
        projector_for(model.config.projector, dev), model.means.shape[0], model.view_c2w.shape[0], rows, cols
    )
    CONSOLE.print(
        f"gaussian-atoms: {views} views per step (auto, {projector_name(model.config.projector, dev)} projector on "
        f"{dev.type})"
    )
    return views


MAX_VIEWS_PER_STEP = 8
"""``views_per_step auto`` never batches more views than this: more views per step reached the
same precision at the same step, in more GPU memory (docs/performance.md, several views per
step)."""
MEMORY_SHARE = 0.5
"""``auto`` spends at most this share of the free GPU memory on a step's views; the rest stays
for the start's leftovers, the residual search's back-projections and the final stage."""


def projector_bytes_per_view(
    projector, n_gaussians: int, rows: torch.Tensor, cols: torch.Tensor, sample: int = 1024
) -> float:
    """Bytes autograd keeps for one view of ``n_gaussians`` through ``projector`` on the
    detector (``rows``, ``cols``) and device of the coordinates: measured on ``sample`` Gaussians
    in two views (the tensors saved for the backward pass, each storage once) and scaled to
    ``n_gaussians``.  The dense projector keeps a few (N, H) and (N, W) float32 tensors per view."""
    means, sigmas, amplitudes, axes = probe_scene(sample, 2, rows, cols)
    storages: dict[int, int] = {}

    def keep(t: torch.Tensor):
        storages[t.untyped_storage().data_ptr()] = t.untyped_storage().nbytes()
        return t

    with torch.autograd.graph.saved_tensors_hooks(keep, lambda t: t):
        projector(means, sigmas, amplitudes, axes, rows, cols).sum()
    return sum(storages.values()) / 2 * n_gaussians / sample


def auto_views_per_step(projector, n_gaussians: int, n_views: int, rows: torch.Tensor, cols: torch.Tensor) -> int:
    """``views_per_step auto``: 1 off a GPU (each view costs its own time there); on a GPU the
    most views, up to :data:`MAX_VIEWS_PER_STEP` and the series' own, whose projector memory
    (:func:`projector_bytes_per_view`) fits in :data:`MEMORY_SHARE` of the free GPU memory
    (the caching allocator's unused blocks counted free).

    Never by the projector's measured time: a choice by time moved between runs of one input
    (an H200, a 16,000-atom Ni-Pd-Pt particle through ADF physics: 2 views in one run, 4 in the
    next, found 0.921 and 0.957), and the most views also fit best where a view's own work
    dominates (there, 54,000 aPd atoms: 1 view by time, found 0.9988 / 10.5 pm in 84 s; 8 views,
    1.0000 / 8.3 pm in 89 s)."""
    device = rows.device
    if device.type != "cuda":
        return 1
    free = torch.cuda.mem_get_info(device)[0] + torch.cuda.memory_reserved(device) - torch.cuda.memory_allocated(device)
    fits = int(MEMORY_SHARE * free // max(projector_bytes_per_view(projector, n_gaussians, rows, cols), 1.0))
    return max(1, min(MAX_VIEWS_PER_STEP, n_views, fits))


def probe_scene(n_gaussians: int, views: int, rows: torch.Tensor, cols: torch.Tensor):
    """``n_gaussians`` random Gaussians over the detector's extent (learnable, on the
    coordinates' device and dtype) and the detector axes of ``views`` views tilted about y."""
    device, dtype = rows.device, rows.dtype
    generator = torch.Generator().manual_seed(0)
    extent = float(max(rows.abs().max(), cols.abs().max()))
    means = ((torch.rand(n_gaussians, 3, generator=generator) - 0.5) * extent).to(device, dtype).requires_grad_()
    sigmas = torch.full((n_gaussians,), 0.01 * extent, device=device, dtype=dtype, requires_grad=True)
    amplitudes = torch.ones(n_gaussians, device=device, dtype=dtype, requires_grad=True)
    angles = torch.linspace(-1.0, 1.0, views, dtype=dtype)
    axes = torch.stack(
        [
            torch.stack([torch.zeros_like(angles), torch.ones_like(angles), torch.zeros_like(angles)], -1),
            torch.stack([torch.cos(angles), torch.zeros_like(angles), torch.sin(angles)], -1),
        ],
        1,
    ).to(device)
    return means, sigmas, amplitudes, axes


def with_other_views(
    outputs: dict, measured: torch.Tensor, train_projections: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """The step's predicted and ``measured`` (H, W, 1) projections, with its other views'
    (``extra_projection``, ``extra_views``; measured from ``train_projections``, whose device the
    model's index is already on) stacked on a leading axis when it has them."""
    pred = outputs["projection"]
    if "extra_projection" not in outputs:
        return pred, measured
    extra = outputs["extra_projection"]
    extra_gt = binned_views(
        train_projections[index_on(outputs["extra_views"], train_projections.device)], *extra.shape[1:3]
    )[..., None].to(extra)
    return torch.cat([pred[None], extra]), torch.cat([measured[None], extra_gt])


def other_views(view: int, n_views: int, views_per_step: int, generator: torch.Generator) -> torch.Tensor:
    """``views_per_step - 1`` distinct training views other than ``view``, drawn at random."""
    k = min(views_per_step - 1, n_views - 1)
    others = torch.randperm(n_views - 1, generator=generator)[:k]
    return others + (others >= view).long()  # skip ``view`` itself
