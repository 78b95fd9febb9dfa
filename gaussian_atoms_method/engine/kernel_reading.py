"""The point-spread function read on views the atoms were not fitted to (``psf held-out``).

Learned with the atoms from the same views, the kernel loses to the Gaussians: a probe's tails
around an atom can be explained by the kernel or by extra faint Gaussians beside it, and the
extra Gaussians (more parameters) always fit the views they were fitted to at least as well.
Views they were not fitted to tell the two apart.  So until the kernel settles the atoms learn
from the even views only and, every ``refine_every`` steps, the kernel is fitted to the odd
views (the Gaussians held; :func:`gaussian_atoms_method.physics.psf.fit_kernel_weights` under
the run's data term, least squares for L1; the views' backgrounds are fitted on every view:
they are the views' own).  The reading grows as the atoms sharpen (Ta film area 23: no kernel
at step 300, 14% of the intensity in the tails at 1,400, 31% at 2,400), so it is not judged
settled early: at ``stop_split_at`` the kernel is held, and the atoms start again from the
start on every view with the kernel held (:meth:`~.fit.AtomFit.start_again`; the reading pass's
own atoms are not reported).

The reading is the kernel that best predicts the held-out views, so it also hides the half-view
fit's own errors: where that fit is poor it is too wide (a 54,000-atom a-Pd particle with no tails
in its physics, 24 limited tilts a half, read 53% of the intensity at 2 Å and lost 0.03 in TPR).
"""

from __future__ import annotations

import torch

from gaussian_atoms_method.engine.console import CONSOLE
from gaussian_atoms_method.physics.data_terms import data_term
from gaussian_atoms_method.physics.psf import fit_kernel_weights


class HeldOutKernel:
    """The schedule: which views teach the atoms, and when the kernel is read.  Inactive (any
    other ``psf``): every view teaches the atoms and nothing is read."""

    def __init__(self, n_views: int, stop_at: int, active: bool = True):
        self.n_views, self.stop_at = n_views, stop_at
        self.settled = not active or n_views < 2  # a single view has nothing to hold out
        self.first_pass = not self.settled  # the reading pass: its atoms are not reported

    def splitting(self, step: int) -> bool:
        """True while the odd views are held out of the atoms' fit."""
        return not self.settled and step < self.stop_at

    def holds_out(self, view: int | None, step: int) -> bool:
        """True for a view the atoms must not learn from at ``step`` (odd views, while splitting)."""
        return self.splitting(step) and view is not None and view % 2 == 1

    def other_views(self, view: int, views_per_step: int, generator: torch.Generator, step: int) -> torch.Tensor:
        """The other views of a step with ``view`` (:func:`gaussian_atoms_method.engine.step_views.other_views`): while
        splitting, even views only."""
        from gaussian_atoms_method.engine.step_views import other_views

        if self.splitting(step):
            return 2 * other_views(view // 2, (self.n_views + 1) // 2, views_per_step, generator)
        return other_views(view, self.n_views, views_per_step, generator)

    @staticmethod
    def differentiable(loss: torch.Tensor, means: torch.Tensor, held_out: bool) -> torch.Tensor:
        """``loss`` with a gradient path: through ``means`` (+ 0 x their sum, so a run whose
        Gaussians were all pruned can still step), or on a held-out view through nothing of the
        atoms, which then get no gradient (not a zero one: Adam and the densify statistics would
        count that)."""
        if not held_out:
            return loss + 0.0 * means.sum()
        return loss if loss.requires_grad else loss + torch.zeros((), device=loss.device, requires_grad=True)

    @torch.no_grad()
    def read(self, model, step: int, warmup: int = 0, every: int = 1) -> None:
        """At a refine step (every ``every`` from ``warmup``) while splitting: fit the kernel to
        the held-out views and set it; at ``stop_at``: hold it."""
        if self.settled or step < warmup or step % every != 0:
            return
        if step >= self.stop_at:
            self._settle(model, step)
            return
        fitted = read_kernel(model, range(1, self.n_views, 2))
        if fitted is not None:
            model.view_params["psf"].data.copy_(fitted.to(model.view_params["psf"]))

    def _settle(self, model, step: int) -> None:
        self.settled = True
        fractions = ", ".join(f"{w:.3f}" for w in model.view_params["psf"].detach().cpu().tolist())
        CONSOLE.print(
            f"gaussian-atoms: step {step}: the point-spread function read on the held-out views is held at {fractions} "
            f"(1, 2, 4 Å)"
        )


def read_kernel(model, views) -> torch.Tensor | None:
    """(K,) the kernel's weights fitted to ``views`` with the model's Gaussians and backgrounds
    held, under the model's data term; None without the tilt series."""
    from gaussian_atoms_method.engine.residuals import training_views

    measured_all = model.view_set.projections
    weights = model.view_params["psf"]
    if measured_all is None or model.num_points == 0:
        return None
    held = weights.data.clone()
    images, backgrounds = [], []
    try:
        with training_views(model) as cameras:
            if cameras is None:
                return None
            weights.data.zero_()  # the kernel-free rendering, its background apart
            for v in views:
                out = model.get_outputs(cameras[v : v + 1], background=False)
                images.append(out["projection"][..., 0])
                backgrounds.append(out["background"][..., 0] if "background" in out else torch.zeros_like(images[-1]))
    finally:
        weights.data.copy_(held)
    images, backgrounds = torch.stack(images), torch.stack(backgrounds)
    measured = torch.as_tensor(measured_all[list(views)]).to(images)
    noise = model.noise_read
    gain, read_var = (noise.gain, noise.read_var) if noise else (1.0, 0.0)
    spacing = float(model.view_set.pixel_size_A) * model.normalisation.length_scale
    kind = "l2" if model.data_term == "l1" else model.data_term  # L1's curvature is zero: no Newton step
    return fit_kernel_weights(
        images,
        backgrounds,
        measured,
        spacing,
        model.psf_widths.to(images),
        lambda p, m: data_term(p, m, kind, gain, read_var),
    )
