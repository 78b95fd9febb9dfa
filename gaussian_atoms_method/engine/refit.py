"""The refit after the final prune and merge
(:meth:`gaussian_atoms_method.nerfstudio_layer.model.GaussianAtomsModel.finalize`):
the survivors take up what the removed Gaussians carried."""

from __future__ import annotations

import numpy as np
import torch

from gaussian_atoms_method.density.averaging import IterateAverage
from gaussian_atoms_method.engine.convergence import drifting
from gaussian_atoms_method.engine.progress import ProgressBar
from gaussian_atoms_method.engine.rendering import index_on, render_views, view_floors
from gaussian_atoms_method.engine.residuals import in_chunks, measured_views, training_views


def refit(
    model,
    max_passes: int = 10,
    measured: torch.Tensor | None = None,
    until_still: bool = False,
    progress: bool = False,
    what: str = "gaussian-atoms: final refit",
    in_logs: bool = True,
    noise: float | None = None,
    window: tuple[int, slice] | None = None,
) -> int:
    """After the final prune and merge: passes over the training views in random order at full
    resolution, as many views per step as training took, with the model's own optimisers (their
    rates where training left them) and no density control, until the atoms settle two passes in
    a row (at most ``max_passes``); the steps taken (0 without the tilt series).

    Settled, per atom as the training's stop (:mod:`.convergence`): no more than the false
    discovery rate's share of the atoms move by more than their Cramér-Rao precision between
    passes' means, or the means only scatter, no longer drift (:func:`.convergence.drifting`).
    The positions are then the mean over those passes and the one before (unsettled: over the
    second half of the passes, the first half being the transient).

    Why passes: a merged atom sits at its members' mass-weighted mean, where the data put it only
    when the members were fragments of one atom.  Why training's views per step: with one view a
    step after training on eight, the refit's own jitter would undo the training's precision.

    ``measured`` (V, H, W), normalised, on the model's device: views to fit instead of the
    measured ones (the run's own replica, :mod:`.own_floor`).  ``until_still``: settled only
    when the passes' means no longer drift (:func:`.convergence.drifting`), however little each
    atom moves in a pass: the place the views' optimum holds, not one the refit reached.
    ``progress``: a bar of its steps, ended where the atoms settle (on the CPU the Au noise-200
    run's refit takes 8 of its 86 s, which had passed without a sign), named ``what``; ``in_logs``
    False: in a terminal only (:class:`~.progress.ProgressBar`); ``noise``: the pixel noise the
    atoms' precision is judged in (input units; default the residual's at the first pass,
    :func:`.results.residual_noise`); ``window`` (k, cut): only the detector's rows (k 0) or
    columns (k 1) ``cut`` are rendered and fitted (``measured``, where given, holds them alone),
    where the views are rendered together (:func:`.residuals.in_chunks`; ``window`` is then
    :func:`window_of` a band): where the model's Gaussians lie whole within it, the rest of each
    view holds nothing they render (:func:`.own_floor.floor_slab`)."""
    measured_all = measured_views(model) if measured is None else measured
    names = [n for n in model.gauss_params.keys() if n in model.optimizers]
    steps, settled = 0, 0
    with training_views(model) as cameras:
        if cameras is None or measured_all is None:
            return 0
        # Called where results are written: possibly under no_grad or inference mode.
        with torch.inference_mode(False), torch.enable_grad():
            # the start, then each pass's mean; the streak from passes[first]
            passes, first = (
                [model.means.detach().clone()],
                1,
            )
            together = in_chunks(model, cameras)  # a step's views in one projector call, where the cameras allow it
            floors = None  # rendered with the views (None), or held as the views were cut
            if window is not None and together is not None:
                together, floors = _within(model, window, together)
                if measured is None:
                    measured_all = in_window(measured_all, window)
            per_pass = -(-len(cameras) // max(int(model.views_per_step), 1))
            bar = ProgressBar(max_passes * per_pass, what=what, in_logs=in_logs) if progress else None
            for _ in range(max_passes):
                average = IterateAverage() if model.density.average_iterates else None
                steps += _refit_pass(
                    model, cameras, measured_all, names, together, model.views_per_step, average, floors
                )
                if bar is not None:
                    bar.count(steps - 1)
                now = average.mean(model.gauss_params)["means"] if average is not None else model.means.detach().clone()
                moved_A = (now - passes[-1]).norm(dim=1).cpu().numpy() / model.normalisation.length_scale
                result = model.position_std_A(model.atoms(), noise)
                if result is None:
                    break
                std, noise = result
                precision_A = np.sqrt((std**2).sum(axis=1))
                moving = int(np.count_nonzero(moved_A > precision_A))
                means, n = passes + [now], len(passes)  # the start, then each pass's mean; now the n-th
                # a slow drift hides in the scatter between neighbouring passes: over windows that
                # double (passes n/4, n/2, n) it grows with them while the scatter does not
                window = (n // 4, n // 2, n) if until_still else (n - 2, n - 1, n)
                jitter_only = n >= (4 if until_still else 3) and not drifting(
                    *(means[i].cpu().double().numpy() / model.normalisation.length_scale for i in window), precision_A
                )
                few_moving = moving <= model.config.false_discovery_rate * len(moved_A) and not until_still
                settled = settled + 1 if few_moving or jitter_only else 0
                first = first if settled else len(passes)
                passes.append(now)
                if settled >= 2:
                    break
            if bar is not None:
                bar.close()
            # the mean over the settled passes and the one before, or over the second half
            if average is not None and len(passes) > 1:
                model.gauss_params["means"].data.copy_(
                    torch.stack(passes[first:] if settled >= 2 else passes[1:][(len(passes) - 1) // 2 :]).mean(dim=0)
                )
    return steps


def window_of(model, band: tuple[int, float, float]) -> tuple[int, slice] | None:
    """(k, cut): the detector's rows (``band[0]`` 0) or columns (1) whose coordinates
    (normalised) lie within ``band[1:]``, where the model renders its views together
    (:func:`.residuals.in_chunks`), else None."""
    k, lo, hi = band
    with training_views(model) as cameras:
        together = None if cameras is None else in_chunks(model, cameras)
    if together is None:
        return None
    inside = torch.nonzero((together[k] >= lo) & (together[k] <= hi)).flatten().tolist()
    return (k, slice(inside[0], inside[-1] + 1)) if inside else None


def in_window(views, window: tuple[int, slice] | None):
    """``views`` (V, H, W), an array or a tensor, cut to ``window`` (k, cut): the detector's rows
    (k 0) or columns (k 1) ``cut``; None: as they are.

    >>> in_window(np.zeros((2, 5, 6)), (1, slice(1, 4))).shape
    (2, 5, 3)
    """
    if window is None:
        return views
    k, cut = window
    return views[:, cut] if k == 0 else views[:, :, cut]


def _within(model, window: tuple[int, slice], together):
    """``together`` (:func:`.residuals.in_chunks`) cut to the detector's rows (``window[0]`` 0)
    or columns (1) ``window[1]``, and the views' floors (V, h, w) as cut (None without floors):
    the refit holds them as they are (the model in eval mode), and a floor surface is read off
    the whole detector."""
    k, cut = window
    rows, cols, pitch, chunks = together
    floors = None
    if "background" in model.view_params:
        with torch.no_grad():
            powers = model.view_geometry.powers(rows, cols)
            floors = in_window(
                view_floors(model, list(range(model.view_c2w.shape[0])), powers, model.means.dtype), window
            )
    rows, cols = (rows[cut], cols) if k == 0 else (rows, cols[cut])
    return (rows, cols, pitch, chunks), floors


def _refit_pass(
    model,
    cameras,
    measured_all: torch.Tensor,
    names,
    together,
    views_per_step: int = 1,
    average: IterateAverage | None = None,
    floors: torch.Tensor | None = None,
) -> int:
    """One pass over the views, ``views_per_step`` per step (the mean of their losses, as
    training's one loss over a step's views), fitted to ``measured_all`` (V, H, W) on the model's
    device (once a refit: a copy of a step's views at each step would wait for the queued step),
    rendered ``together`` (:func:`.residuals.in_chunks`; None: view by view) with their own
    floors, or with ``floors`` (V, H, W) as given, each iterate added to ``average``; returns the
    steps taken."""
    # Views in random order, as training draws them: in tilt order neighbouring views pull
    # alike and Adam's momentum carries the atoms along (the aPd noise-200 RMSD rose 1.2 pm).
    order, size = torch.randperm(len(cameras), generator=model.generator), max(int(views_per_step), 1)
    order_on_device = index_on(order, measured_all.device)  # copied without waiting for the queued steps
    starts = range(0, len(order), size)
    for start in starts:
        batch = order[start : start + size]
        for n in names:
            model.optimizers[n].zero_grad()
        if together is not None:  # the data term's mean over all the step's pixels: the mean of its views' (one size)
            index = order_on_device[start : start + size]
            rendered = (
                render_views(model, index, *together[:3])
                if floors is None
                else render_views(model, index, *together[:3], floors=False) + floors[index]
            )
            loss = model.get_loss_dict(
                {"projection": rendered[..., None]},
                {"image": measured_all[index][..., None]},
            )["main_loss"]
        else:
            loss = sum(
                model.get_loss_dict(model.get_outputs(cameras[v : v + 1]), {"image": measured_all[v][..., None]})[
                    "main_loss"
                ]
                for v in batch.tolist()
            ) / len(batch)
        loss.backward()
        for n in names:
            model.optimizers[n].step()
        with torch.no_grad():
            model.density.clamp(model.gauss_params)
        if average is not None:
            average.add(model.gauss_params)
    return len(starts)
