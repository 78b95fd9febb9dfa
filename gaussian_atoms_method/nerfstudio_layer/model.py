"""``GaussianAtomsModel``: the fit (:class:`~gaussian_atoms_method.engine.fit.AtomFit`) as a
splatfacto model, for nerfstudio's trainer, viewer and exporters.

The fit's own methods come first (it is the first base), so rendering, loss, density control,
the stop and the files are the engine's; this adapter adds what nerfstudio asks of a model:
building from the dataparser's metadata, the training callbacks at nerfstudio's places, the
evaluation images, and the atoms as points in the viewer.  splatfacto's per-Gaussian properties
are :class:`.splatfacto_compat.SplatfactoCompat`'s.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Tuple, Type

import torch
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation

from gaussian_atoms_method.engine.console import CONSOLE
from gaussian_atoms_method.engine.fit import AtomFit
from gaussian_atoms_method.engine.view_set import ViewSet
from gaussian_atoms_method.launch.start_ahead import prepared
from gaussian_atoms_method.nerfstudio_layer.options import GaussianAtomsOptions
from gaussian_atoms_method.nerfstudio_layer.splatfacto_compat import SplatfactoCompat
from gaussian_atoms_method.nerfstudio_layer.viewer import AtomsInViewer
from gaussian_atoms_method.physics.devices import run_on
from gaussian_atoms_method.physics.units import DATA_RANGE


class TrainingSpan:
    """The steps of one of nerfstudio's training loops: ``see`` (a before-step callback) takes
    the first step it is called at, and ``last`` is that plus ``iterations`` - 1 (a loop
    resumed from a checkpoint starts past 0).  Read from the steps themselves, not the
    trainer's private start."""

    def __init__(self, iterations: int) -> None:
        self.iterations, self.first = int(iterations), None

    def see(self, step: int) -> None:
        if self.first is None:
            self.first = int(step)

    @property
    def last(self) -> int:
        return (0 if self.first is None else self.first) + self.iterations - 1


@dataclass
class GaussianAtomsModelConfig(GaussianAtomsOptions):
    """Gaussian atoms: isotropic 3D Gaussians fitted to a tilt series."""

    _target: Type = field(default_factory=lambda: GaussianAtomsModel)


class GaussianAtomsModel(AtomFit, SplatfactoCompat):
    """The fit, built by nerfstudio's pipeline and trained by its trainer."""

    config: GaussianAtomsModelConfig

    def __init__(self, *args, **kwargs) -> None:
        SplatfactoCompat.__init__(self, *args, **kwargs)  # nerfstudio's Model: config, scene box, metadata

    def populate_modules(self) -> None:
        # Deliberately not splatfacto's: that builds LPIPS (downloads weights), SH colours,
        # opacities and gsplat's alpha-compositing strategy, none of which apply here.
        self.prepared = prepared()  # the start ns-train began while it loaded (config.py)
        with run_on(self.run_device):
            self.setup(ViewSet.from_metadata(self.kwargs.get("metadata")))  # the views read once
        self.crop_box, self.background_color = None, torch.zeros(3)
        if not hasattr(self, "atoms_in_viewer"):  # the atoms as points in the viewer
            self.atoms_in_viewer = AtomsInViewer(self._viewer_atoms)

    def atoms_changed(self) -> None:
        self.atoms_in_viewer.refresh()

    def get_image_metrics_and_images(self, outputs, batch) -> Tuple[Dict[str, float], Dict[str, torch.Tensor]]:
        gt, pred = batch["image"].to(outputs["projection"]), outputs["projection"]
        mse = torch.mean((pred - gt) ** 2)
        metrics = {
            "l1": float(torch.abs(pred - gt).mean()),
            "psnr": float(10 * torch.log10(DATA_RANGE**2 / mse.clamp_min(1e-12))),
            "gaussian_count": float(self.num_points),
        }
        return metrics, {"img": (torch.cat([gt, pred], dim=1) / DATA_RANGE).clamp(0, 1).expand(-1, -1, 3)}

    def get_training_callbacks(
        self, training_callback_attributes: TrainingCallbackAttributes
    ) -> List[TrainingCallback]:
        """The fit's work around each step at nerfstudio's places, in the engine loop's order
        (:func:`gaussian_atoms_method.engine.training.after_step`)."""
        attrs, after = training_callback_attributes, [TrainingCallbackLocation.AFTER_TRAIN_ITERATION]
        cbs = [
            TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], self.step_cb, args=[attrs.optimizers]),
            TrainingCallback(after, self.refine_after_step),
            TrainingCallback(after, self.merge_after_step),
        ]
        trainer = attrs.trainer
        if trainer is not None:
            span = TrainingSpan(trainer.config.max_num_iterations)
            cbs.insert(0, TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], span.see))
            cbs.append(TrainingCallback(after, self._results_at, args=[span, trainer.base_dir]))
            cbs.append(TrainingCallback(after, self._stop_trainer, args=[trainer, span]))
            cbs.append(TrainingCallback(after, self._say_viewer, args=[trainer, span]))
            if self.config.snapshot_every > 0:
                cbs.append(
                    TrainingCallback(after, self.snapshot_after_step, args=[Path(trainer.base_dir) / "snapshots"])
                )
        return cbs

    @property
    def run_device(self) -> str:
        """The device nerfstudio's pipeline builds the model for (its helpers keep to the CPU
        with a CPU run: :func:`~gaussian_atoms_method.physics.devices.run_on`)."""
        return str(self.kwargs.get("device") or "cuda")

    def _results_at(self, span: TrainingSpan, run_dir, step: int) -> None:
        with run_on(self.run_device):
            self.write_results_at(span.last, run_dir, step)

    def _stop_trainer(self, trainer, span: TrainingSpan, step: int) -> None:
        progress = getattr(trainer, "progress", None)
        with run_on(self.run_device):
            stop = self.should_stop(step, span.last, Path(trainer.base_dir), progress)
        if stop:
            trainer.stop_training = True  # nerfstudio's loop ends before the next step

    def _say_viewer(self, trainer, span: TrainingSpan, step: int) -> None:
        """Once the results are written (the last step, or the trainer stopped early): where a
        viewer keeps serving after training, say where and how to stop it."""
        viewer, config = getattr(trainer, "viewer_state", None), trainer.config.viewer
        over = (step >= span.last or trainer.stop_training) and not self.kernel_reading.first_pass
        over = over and not getattr(self, "second_look_pending", False)
        if viewer is None or config.quit_on_train_completion or not over:
            return
        where = "; ".join(getattr(viewer, "viewer_info", None) or [str(getattr(viewer, "viewer_url", "its address"))])
        CONSOLE.print(f"gaussian-atoms: training is over and the viewer keeps serving ({where}): stop it with Ctrl-C")
