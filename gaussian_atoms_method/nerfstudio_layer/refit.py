"""The short refit after the final prune and merge (:meth:`.model.GaussianAtomsModel.finalize`):
the survivors take up what the removed Gaussians carried."""

from __future__ import annotations

import torch

from gaussian_atoms_method.nerfstudio_layer.residuals import training_views


def refit(model, passes: int = 1) -> int:
    """After the final prune and merge: ``passes`` passes over the training views, one view
    per step in random order at full resolution, updating the Gaussians with the model's own
    optimisers (their learning rates where training left them) and no density control.  A
    merged atom sits at its members' mass-weighted mean, which is where the data put it only
    when the members were fragments of one atom; one pass of 40-60 views moves it the rest of
    the way at a cost of a few tenths of a per cent of a 3,000-step run.  Returns the steps
    taken (0 without the tilt series)."""
    projections = (model.kwargs.get("metadata", {}) or {}).get("projections")
    names = [n for n in model.gauss_params.keys() if n in model.optimizers]
    with training_views(model) as cameras:
        if cameras is None or projections is None:
            return 0
        # Called where results are written: possibly under no_grad or inference mode.
        with torch.inference_mode(False), torch.enable_grad():
            _refit_steps(model, cameras, projections, names, passes)
    return passes * len(cameras)


def _refit_steps(model, cameras, projections, names, passes: int) -> None:
    # Views in random order, as training draws them: in tilt order neighbouring views pull
    # alike and Adam's momentum carries the atoms along (the aPd noise-200 RMSD rose 1.2 pm).
    order = torch.cat([torch.randperm(len(cameras), generator=model.generator) for _ in range(passes)])
    for v in order.tolist():
        for n in names:
            model.optimizers[n].zero_grad()
        target = projections[v].to(model.means.device)[..., None]
        model.get_loss_dict(model.get_outputs(cameras[v : v + 1]), {"image": target})["main_loss"].backward()
        for n in names:
            model.optimizers[n].step()
        with torch.no_grad():
            model.density.clamp(model.gauss_params)
