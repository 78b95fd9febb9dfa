"""``GaussianAtomsModel``: splatfacto with the tomographic projector in place of the rasteriser.

One isotropic Gaussian per atom.  Parameters (normalised units, see
:mod:`gaussian_atoms_method.physics.units`):

* ``means`` (N, 3): positions;
* ``log_sigmas`` (N, 1): one width per Gaussian, ``sigma = exp(log_sigma)`` (the isotropy
  prior); with ``isotropic=False`` (the ablation) three widths (N, 3) and a rotation ``quats``
  (N, 4), projected exactly by :func:`~gaussian_atoms_method.physics.projector.project_anisotropic_gaussians`;
* ``log_amplitudes`` (N, 1): the 3D peak, ``q = exp(log_amplitude)``.  The exponential keeps it
  positive and makes Adam's steps relative, so faint and bright atoms learn at the same pace.

The model keeps the rendering (composed from :mod:`gaussian_atoms_method.engine.rendering`) and the loss (the data term
chosen from the measured noise, :mod:`gaussian_atoms_method.engine.noise_reading`; no SSIM, LPIPS, SH or alpha).  How
many
Gaussians exist is :mod:`gaussian_atoms_method.density.strategy`'s, called from the callbacks
registered here; the start :mod:`gaussian_atoms_method.atoms.initialise`'s, the stop
:mod:`gaussian_atoms_method.engine.convergence`'s, the files :mod:`gaussian_atoms_method.engine.results`'.  Options:
:mod:`.options`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Dict, List, Tuple, Type

import torch
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from torch.nn import Parameter

from gaussian_atoms_method.atoms.atom_set import AtomSet, read_atoms
from gaussian_atoms_method.atoms.initialise import compute_start, starting_amplitude
from gaussian_atoms_method.density.parameters import amplitudes, widths
from gaussian_atoms_method.density.strategy import DensityControl
from gaussian_atoms_method.engine import rendering as R
from gaussian_atoms_method.engine import step_views as SV
from gaussian_atoms_method.engine.console import CONSOLE
from gaussian_atoms_method.engine.convergence import ConvergenceCheck
from gaussian_atoms_method.engine.floors import FloorSolver
from gaussian_atoms_method.engine.kernel_reading import HeldOutKernel
from gaussian_atoms_method.engine.noise_reading import judge_after_fit, read_noise, say_hard_core, say_start
from gaussian_atoms_method.engine.refit import refit
from gaussian_atoms_method.engine.residuals import residual_correlations
from gaussian_atoms_method.engine.results import model_position_std_A, write_results, write_snapshot
from gaussian_atoms_method.engine.stopping import at_check, set_position_rate
from gaussian_atoms_method.engine.view_set import ViewSet
from gaussian_atoms_method.nerfstudio_layer.checkpoints import allow_numpy_scalars_in_checkpoints
from gaussian_atoms_method.nerfstudio_layer.options import GaussianAtomsOptions
from gaussian_atoms_method.nerfstudio_layer.splatfacto_compat import SplatfactoCompat
from gaussian_atoms_method.nerfstudio_layer.step_graph import StepGraph
from gaussian_atoms_method.nerfstudio_layer.viewer import AtomsInViewer
from gaussian_atoms_method.physics.data_terms import data_term
from gaussian_atoms_method.physics.psf import project_weights
from gaussian_atoms_method.physics.units import DATA_RANGE, Normalisation
from gaussian_atoms_method.start_ahead import take as take_start


@dataclass
class GaussianAtomsModelConfig(GaussianAtomsOptions):
    """Gaussian atoms: isotropic 3D Gaussians fitted to a tilt series."""

    _target: Type = field(default_factory=lambda: GaussianAtomsModel)


class GaussianAtomsModel(SplatfactoCompat):
    """Splatfacto subclass (through :class:`.splatfacto_compat.SplatfactoCompat`) whose renderer
    is the tomographic line-integral projector."""

    config: GaussianAtomsModelConfig

    # ------------------------------------------------------------------ set-up
    def populate_modules(self) -> None:
        # Deliberately not splatfacto's: that builds LPIPS (downloads weights), SH colours,
        # opacities and gsplat's alpha-compositing strategy, none of which apply here.
        allow_numpy_scalars_in_checkpoints()  # nerfstudio loads checkpoints after building the model
        cfg = self.config
        cfg.check()
        views = self.view_set = ViewSet.from_metadata(self.kwargs.get("metadata"))  # read once
        self.normalisation: Normalisation = views.normalisation or Normalisation(1.0, 1.0)
        ls, series = self.normalisation.length_scale, views.series
        self.generator = torch.Generator().manual_seed(cfg.seed)
        projections, start_options = (
            views.projections,
            (self.normalisation, cfg.extended_object, cfg.max_atom_sigma_A),
        )
        given = read_atoms(cfg.start_atoms).positions if cfg.start_atoms is not None else None
        # begun while the launcher loaded
        ahead = (
            take_start(series, projections, *start_options) if cfg.init == "backprojection" and given is None else None
        )
        start = ahead or compute_start(
            series,
            projections,
            *start_options,
            cfg.init == "backprojection",
            cfg.num_random,
            cfg.init_extent,
            self.generator,
            positions_A=given,
        )
        say_start(start, ls, cfg.extended_object, ahead is not None)
        measured, means, weights, half_extent, self.field_half_extent = (
            start.noise,
            start.means,
            start.weights,
            start.field.half_extent,
            start.field.field_half_extent,
        )
        n, sigma0 = means.shape[0], cfg.init_sigma_A * ls
        amp0 = starting_amplitude(
            projections,
            views.pixel_size_A,
            ls if views.normalisation else None,
            n,
            sigma0,
            DATA_RANGE,
        )
        log_amps = torch.full((n, 1), math.log(amp0))
        if weights is not None and cfg.init_mass == "backprojection":
            log_amps += torch.log(weights)[:, None]
        params = {
            "means": Parameter(means),
            "log_sigmas": Parameter(torch.full((n, 1 if cfg.isotropic else 3), math.log(sigma0))),
            "log_amplitudes": Parameter(log_amps),
        }
        if not cfg.isotropic:  # near-identity rotations; exactly identity would start every ellipsoid axis-aligned
            params["quats"] = Parameter(
                torch.tensor([1.0, 0.0, 0.0, 0.0]) + 0.1 * torch.randn(n, 4, generator=self.generator)
            )
        self.gauss_params = torch.nn.ParameterDict(params)
        # Every Gaussian's mass stays below 1000x the whole measured mass (DensityControl.clamp).
        max_log_amp = math.log(1000.0 * max(n, 1) * amp0 * (sigma0 / (cfg.min_sigma_A * ls)) ** 3)
        self.density = DensityControl(
            ls,
            max_log_amp,
            self.generator,
            half_extent=half_extent,
            field_half_extent=self.field_half_extent if half_extent != self.field_half_extent else None,
            **{f.name: getattr(cfg, f.name) for f in fields(DensityControl) if hasattr(cfg, f.name)},
        )
        self.density.reset(n)
        self.density.hard_core_A = say_hard_core(series.species if series is not None else ())
        self.convergence = ConvergenceCheck(
            cfg.warmup_length,
            cfg.refine_every,
            cfg.converged_fraction,
            cfg.false_discovery_rate,
            cfg.merge_threshold_A * ls,
        )
        self.noise_read, self.data_term, floor, surfaces = read_noise(
            views.projections, cfg.loss, cfg.background, measured
        )
        self._setup_view_params(views, floor, surfaces)
        if self.noise_read is not None and views.pixel_size_A:  # the prune judges masses against this noise
            self.density.set_noise(
                self.noise_read,
                floor or 0.0,
                views.pixel_size_A * ls,
                self.view_c2w.shape[0],
                self.data_term,
                self.view_c2w[:, :3, 2],
            )
        self.step, self.optimizers, self._optimizers_obj, self._held_out_step, self.kernel_reading = (
            0,
            {},
            None,
            False,
            HeldOutKernel(self.view_c2w.shape[0], self.density.stop_split_at, cfg.psf == "held-out"),
        )
        # the atoms as points in the viewer
        self.crop_box, self.background_color, self.atoms_in_viewer = (
            None,
            torch.zeros(3),
            AtomsInViewer(self._viewer_atoms),
        )
        # read once per view; judged without waiting for the GPU; a step as a CUDA graph
        self.view_geometry, self.finite_watch, self.floors, self.step_graph = (
            R.ViewGeometry(),
            R.FiniteWatch(),
            FloorSolver(),
            StepGraph(),
        )

    def _setup_view_params(self, views: ViewSet, floor: float | None, surfaces=None) -> None:
        """Per-view parameters and the views-per-step batches; a background (solved in closed form,
        :mod:`gaussian_atoms_method.engine.floors`) starts at ``floor``, on the (V, H, W) ``surfaces`` of a floor that
        varies within the views."""
        cfg, view_c2w, series = self.config, views.view_c2w, views.series
        self.register_buffer(
            "view_c2w", view_c2w.float() if view_c2w is not None else torch.zeros(0, 3, 4), persistent=False
        )
        view_params, buffers = R.view_parameters(
            cfg, self.view_c2w.shape[0], floor, surfaces, series, self.normalisation.length_scale
        )
        for name, value in buffers.items():
            self.register_buffer(name, value, persistent=False)
        # read here, on the host: a read from the GPU each step waited for it
        self.psf_widths_host = tuple(buffers["psf_widths"].tolist()) if "psf_widths" in buffers else ()
        self.view_params = torch.nn.ParameterDict(view_params)
        batches, self._views_per_step = SV.view_batches(cfg, views.projections, self.view_c2w)
        # a training step's views by one device index (get_outputs)
        self.indexed_views = not cfg.per_view_options() and SV.on_beam_axes(self.view_c2w)
        self.register_buffer("train_projections", batches, persistent=False)

    @property
    def truth_path(self) -> Path | None:
        """The input's truth file, if it has one (the view set's)."""
        return self.view_set.truth_path

    @property
    def views_per_step(self) -> int:
        """Views fitted per training step (auto: resolved at the first training step,
        :func:`gaussian_atoms_method.engine.step_views.first_step_views`)."""
        if self._views_per_step is None and self.training:
            self._views_per_step = SV.first_step_views(self)
        return self._views_per_step or 1

    # ------------------------------------------------------------------ parameters
    @property
    def means(self) -> torch.Tensor:
        return self.gauss_params["means"]

    @property
    def sigmas(self) -> torch.Tensor:
        """(N,) widths; without isotropy the geometric mean of the three (same volume, same mass)."""
        return widths(self.gauss_params, self.density.min_log_sigma)

    def _log_scales(self) -> torch.Tensor:
        return self.gauss_params["log_sigmas"].clamp_min(self.density.min_log_sigma)

    @property
    def amplitudes(self) -> torch.Tensor:
        return amplitudes(self.gauss_params)

    def get_param_groups(self) -> Dict[str, List[Parameter]]:
        return self.get_gaussian_param_groups() | {name: [param] for name, param in self.view_params.items()}

    # ------------------------------------------------------------------ rendering
    def get_outputs(self, camera: Cameras, background: bool = True) -> Dict[str, torch.Tensor]:
        """Project the Gaussians for one camera: ``rgb`` (H, W, 3) in [0, 1] for the viewer, ``projection``
        (H, W, 1) in normalised data units (``background=False``: the view's background apart, in
        ``background``), ``depth``; with views_per_step > 1 the step's other views (``extra_projection``,
        ``extra_views``: on the model's device)."""
        if camera.shape[0] != 1:
            raise ValueError("GaussianAtomsModel renders one camera at a time")
        dev, dt = self.means.device, self.means.dtype
        c2w = camera.camera_to_worlds[0].to(dt)
        rows, cols, pitch, view = self.view_geometry.read(
            camera, c2w, self.training and self.step < self.config.coarse_steps, self.view_c2w, self.training, dev, dt
        )
        # psf held-out: it teaches the kernel, not the atoms
        self._held_out_step, self.rendered_floors = (
            self.training and self.kernel_reading.holds_out(view, self.step),
            None,
        )
        # the step's views by one device index
        indexed = background and self.training and view is not None and self.indexed_views and not self._held_out_step
        extra = {}
        # cameras on their beam axes through the tilt centre: no offset (SV.step_index; a CUDA graph's replays refill
        # it, .step_graph)
        if indexed:
            index = SV.step_index(self, view, dev)
            images = R.render_views(self, index, rows, cols, pitch)
            image, extra = (
                images[0],
                ({"extra_projection": images[1:, :, :, None], "extra_views": index[1:]} if len(images) > 1 else {}),
            )
        else:
            means, sigmas, amps = [
                x.detach() if self._held_out_step else x for x in (self.means, self.sigmas, self.amplitudes)
            ]
            image = R.one_view(self, c2w, view, rows, cols, pitch, means, sigmas, amps)
            if view is not None and "background" in self.view_params:
                with_floor, floors = R.add_view_floors(self, image[None], [view], rows, cols)
                image, extra = (with_floor[0], extra) if background else (image, {"background": floors[0, ..., None]})
        projection, (h, w) = image[..., None], image.shape
        # A line integral has no depth: the image goes behind the viewer's scene (atom points, frustums).
        depth = torch.full((1, 1, 1), 1e3, device=dev, dtype=dt).expand(h, w, 1)
        return {
            "rgb": (projection / DATA_RANGE).clamp(0.0, 1.0).expand(h, w, 3),
            "projection": projection,
            "depth": depth,
            **extra,
        }

    # ------------------------------------------------------------------ losses and metrics
    @staticmethod
    def _measured(outputs, batch) -> torch.Tensor:
        """The measured projection, binned 2 x 2 when the rendering is (coarse phase); made once
        per step (the metrics and the loss both read it) and kept in ``outputs``."""
        return (
            outputs["measured"]
            if "measured" in outputs
            else outputs.setdefault(
                "measured", R.binned_like(batch["image"].to(outputs["projection"]), outputs["projection"])
            )
        )

    def get_metrics_dict(self, outputs, batch) -> Dict[str, torch.Tensor]:
        return {
            "l1": torch.abs(outputs["projection"] - self._measured(outputs, batch)).mean().detach(),
            "gaussian_count": torch.tensor(float(self.num_points)),
        }

    def get_loss_dict(self, outputs, batch, metrics_dict=None) -> Dict[str, torch.Tensor]:
        # one loss over all the step's views
        pred, gt = SV.with_other_views(outputs, self._measured(outputs, batch), self.train_projections)
        self.floors.accumulate(self, pred, gt)  # the rendered views' floors, in closed form
        # + 0 x means: differentiable even when every Gaussian was pruned (a held-out view: no gradient,
        # HeldOutKernel.differentiable)
        noise = self.noise_read
        loss = self.kernel_reading.differentiable(
            data_term(pred, gt, self.data_term, noise.gain if noise else 1.0, noise.read_var if noise else 0.0),
            self.means,
            self._held_out_step,
        )
        self.finite_watch.check(loss, self.gauss_params, gt, self.step)
        return {"main_loss": loss}

    def get_image_metrics_and_images(self, outputs, batch) -> Tuple[Dict[str, float], Dict[str, torch.Tensor]]:
        gt, pred = batch["image"].to(outputs["projection"]), outputs["projection"]
        mse = torch.mean((pred - gt) ** 2)
        metrics = {
            "l1": float(torch.abs(pred - gt).mean()),
            "psnr": float(10 * torch.log10(DATA_RANGE**2 / mse.clamp_min(1e-12))),
            "gaussian_count": float(self.num_points),
        }
        return metrics, {"img": (torch.cat([gt, pred], dim=1) / DATA_RANGE).clamp(0, 1).expand(-1, -1, 3)}

    # ------------------------------------------------------------------ training callbacks
    def get_training_callbacks(
        self, training_callback_attributes: TrainingCallbackAttributes
    ) -> List[TrainingCallback]:
        attrs, after = training_callback_attributes, [TrainingCallbackLocation.AFTER_TRAIN_ITERATION]
        cbs = [
            TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], self.step_cb, args=[attrs.optimizers]),
            TrainingCallback(after, self.refine_after_step),
            TrainingCallback(after, self.merge_after_step),
        ]
        trainer = attrs.trainer
        if trainer is not None:
            last = trainer._start_step + trainer.config.max_num_iterations - 1
            cbs.append(TrainingCallback(after, self._write_results_at, args=[last, trainer.base_dir]))
            # After the refine and merge callbacks: judged on the atoms as they stand.
            cbs.append(TrainingCallback(after, self._stop_if_converged, args=[trainer, last]))
            if self.config.snapshot_every > 0:
                cbs.append(
                    TrainingCallback(after, self._snapshot_after_step, args=[Path(trainer.base_dir) / "snapshots"])
                )
        return cbs

    def step_cb(self, optimizers, step: int) -> None:
        if optimizers is not self._optimizers_obj:
            set_position_rate(self, optimizers)
        self.step, self._optimizers_obj, self.optimizers = step, optimizers, optimizers.optimizers

    def _param_lists(self):  # nerfstudio's second registry of the parameters (Optimizers.parameters), kept in step
        return getattr(self._optimizers_obj, "parameters", None)

    @torch.no_grad()
    def refine_after_step(self, step: int) -> None:
        """Clamp, accumulate the positional gradient and every refine_every steps duplicate and prune."""
        if "psf" in self.view_params:
            project_weights(self.view_params["psf"].data)  # a non-negative kernel (physics/psf.py)
            self.kernel_reading.read(self, step, self.density.warmup_length, self.config.refine_every)
        self.floors.decide(self, step)  # every refine_every steps: one floor for all views, or one each
        if self.density.step_post_backward(self.gauss_params, self.optimizers, step, self._param_lists()):
            self.atoms_in_viewer.refresh()

    @torch.no_grad()
    def merge_after_step(self, step: int) -> None:
        """The minimum-distance prior as its own callback (every merge_every steps after the warm-up)."""
        if self.density.merge_step(self.gauss_params, self.optimizers, step, self._param_lists()):
            self.atoms_in_viewer.refresh()

    @torch.no_grad()
    def finalize(self) -> None:
        """Last merges and prune (one Gaussian per atom; the residual read by
        :func:`gaussian_atoms_method.engine.residuals.residual_correlations`), then a short refit if they changed
        anything."""
        self.finite_watch.flush()
        judge_after_fit(self)
        if (
            self.density.finalize(
                self.gauss_params, self.optimizers, self._param_lists(), lambda m, s: residual_correlations(self, m, s)
            )
            and self.optimizers
            and self.config.final_refit
        ):
            refit(self)
        self.atoms_in_viewer.refresh()

    # ------------------------------------------------------------------ results
    @torch.no_grad()
    def atoms(self, params=None) -> AtomSet:
        """The current Gaussians (or ``params``, a dict like ``gauss_params``) as atoms in Å, in the frame of the
        input's truth file."""
        norm, host, p = self.normalisation, lambda t: t.detach().cpu().double().numpy(), params or self.gauss_params
        return AtomSet(
            positions=norm.positions_to_A(host(p["means"])),
            sigmas=norm.sigmas_to_A(host(widths(p, self.density.min_log_sigma))),
            amplitudes=norm.amplitudes_to_physical(host(amplitudes(p))),
        )

    def position_std_A(self, atoms: AtomSet, noise: float | None = None):
        """Each atom's position precision (N, 3) in Å and the pixel noise assumed
        (:mod:`gaussian_atoms_method.engine.results`)."""
        return model_position_std_A(self, atoms, noise)

    def converged(self, step: int) -> bool:
        """True once the atoms are settled (:mod:`gaussian_atoms_method.engine.convergence`)."""
        worth = self.density.atoms_worth(self.gauss_params) if self.convergence.checks(step) else None
        return self.convergence.update(
            step,
            self.means,
            self.normalisation.length_scale,
            lambda noise: self.position_std_A(self.atoms(), noise),
            worth,
        )

    def write_results(self, run_dir: Path) -> dict | None:
        """atoms.xyz, atoms.csv, slices.png and evaluation.json
        (:func:`gaussian_atoms_method.engine.results.write_results`)."""
        return write_results(self, Path(run_dir))

    def _write_results_at(self, last_step: int, run_dir: Path, step: int) -> None:
        if step == last_step and not self.kernel_reading.first_pass:
            self.write_results(Path(run_dir))

    def _stop_if_converged(self, trainer, last_step: int, step: int) -> None:
        """At each check: stop once the atoms are settled, else search, settle the set or slow the positions
        (:mod:`gaussian_atoms_method.engine.stopping`)."""
        # psf held-out: the reading ends once the kernel is held (.kernel_reading.restart_with_kernel_held)
        if self.kernel_reading.first_pass:
            trainer.stop_training = self.kernel_reading.settled
        elif at_check(self, step, last_step):
            if getattr(trainer, "progress", None) is not None:  # the bar ends here, before the results print
                trainer.progress.end_at(step)
            CONSOLE.print(f"gaussian-atoms: converged at step {step}: stopping early ({self.convergence.summary()})")
            self.converged_at = step
            self.write_results(Path(trainer.base_dir))
            trainer.stop_training = True  # nerfstudio's loop ends before the next step

    def _snapshot_after_step(self, directory: Path, step: int) -> None:  # after step k*N-1, k*N steps are done
        if (step + 1) % self.config.snapshot_every == 0:
            params = self.density.state.average.mean(self.gauss_params)
            in_field = self.density.in_field(params["means"]).cpu().numpy()  # the mean is detached
            write_snapshot(
                self.atoms(params),
                directory,
                step + 1,
                self.num_points,
                torch.cuda.max_memory_allocated() if self.means.is_cuda else 0,
                in_field,
            )
