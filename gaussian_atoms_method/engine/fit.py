"""``AtomFit``: the fit itself, one isotropic Gaussian per atom, in plain torch.

One object owns the parameters and the view set (:class:`~.view_set.ViewSet`, read once from
the tilt series): the start, the rendering (:mod:`.rendering`), the loss (the data term chosen
from the measured noise, :mod:`.noise_reading`), density control
(:mod:`gaussian_atoms_method.density.strategy`, a strategy with its own state), the stop
(:mod:`.convergence`) and the files (:mod:`.results`).  :mod:`.training` runs it;
nerfstudio's model (:mod:`gaussian_atoms_method.nerfstudio_layer.model`) is this object seen
through splatfacto's interface.

Parameters (normalised units, see :mod:`gaussian_atoms_method.physics.units`):

* ``means`` (N, 3): positions;
* ``log_sigmas`` (N, 1): one width per Gaussian, ``sigma = exp(log_sigma)`` (the isotropy
  prior); with ``isotropic=False`` (the ablation) three widths (N, 3) and a rotation ``quats``
  (N, 4);
* ``log_amplitudes`` (N, 1): the 3D peak, ``q = exp(log_amplitude)``.  The exponential keeps it
  positive and makes Adam's steps relative, so faint and bright atoms learn at the same pace.
"""

from __future__ import annotations

import math
import time
from dataclasses import fields
from pathlib import Path
from typing import Dict, List

import torch
from torch.nn import Parameter

from gaussian_atoms_method.atoms.atom_set import AtomSet
from gaussian_atoms_method.atoms.initialise import compute_start, starting_amplitude
from gaussian_atoms_method.density.parameters import amplitudes, widths
from gaussian_atoms_method.density.settings import DensitySettings
from gaussian_atoms_method.density.strategy import DensityControl
from gaussian_atoms_method.engine import rendering as R
from gaussian_atoms_method.engine import step_views as SV
from gaussian_atoms_method.engine.checkpoints import allow_numpy_scalars_in_checkpoints, with_background_terms
from gaussian_atoms_method.engine.console import CONSOLE
from gaussian_atoms_method.engine.convergence import ConvergenceCheck
from gaussian_atoms_method.engine.floors import FloorSolver
from gaussian_atoms_method.engine.kernel_reading import HeldOutKernel
from gaussian_atoms_method.engine.noise_reading import (
    NoiseReadingBeside,
    read_after_fit,
    say_noise_reading,
    say_series,
    say_start,
    species_rules,
)
from gaussian_atoms_method.engine.options import FitOptions
from gaussian_atoms_method.engine.prepared import NOTHING, Prepared
from gaussian_atoms_method.engine.refit import refit
from gaussian_atoms_method.engine.residuals import residual_correlations
from gaussian_atoms_method.engine.results import model_position_std_A, write_results, write_snapshot
from gaussian_atoms_method.engine.second_look import look_again, start_positions
from gaussian_atoms_method.engine.step_graph import StepGraph
from gaussian_atoms_method.engine.stopping import at_check, converged, set_position_rate
from gaussian_atoms_method.engine.view_set import ViewSet
from gaussian_atoms_method.physics.data_terms import data_term
from gaussian_atoms_method.physics.noise import measure_noise
from gaussian_atoms_method.physics.psf import project_weights
from gaussian_atoms_method.physics.units import DATA_RANGE, Normalisation


class AtomFit(torch.nn.Module):
    """The Gaussians fitted to ``views`` with ``config`` (:class:`~.options.FitOptions`).

    Built without arguments it is empty (nerfstudio's model builds it, then :meth:`setup`)."""

    config: FitOptions
    snapshots_s: float = 0.0
    """Seconds the run's snapshots have cost it so far (:meth:`snapshot_after_step`)."""
    kept: bool = True
    """Whether the run's directory outlives the call (not for ``ga.reconstruct`` without ``output_dir``)."""
    progress: bool = True  # whether the end of the run draws its bars (the final refit's, the evidence's)
    prepared: Prepared = NOTHING
    """What a launcher prepared for this fit while it started (:mod:`.prepared`)."""

    def __init__(
        self, config: FitOptions | None = None, views: ViewSet | None = None, prepared: Prepared = NOTHING
    ) -> None:
        super().__init__()
        self.prepared = prepared
        if config is not None:
            self.config = config
            self.setup(views or ViewSet())

    def atoms_changed(self) -> None:
        """Called whenever Gaussians were added, removed or joined (the viewer redraws its atoms)."""

    def forward(self, camera) -> Dict[str, torch.Tensor]:
        return self.get_outputs(camera)

    @property
    def num_points(self) -> int:
        return self.means.shape[0]

    # ------------------------------------------------------------------ set-up
    def setup(self, views: ViewSet) -> None:
        """Build the start, the parameters, density control and the noise model from ``views``
        (again at a restart, :meth:`start_again`)."""
        allow_numpy_scalars_in_checkpoints()  # checkpoints are loaded after the fit is built
        cfg = self.config
        cfg.check()
        self.view_set = views
        self.normalisation: Normalisation = views.normalisation or Normalisation(1.0, 1.0)
        ls, series = self.normalisation.length_scale, views.series
        self.generator = torch.Generator().manual_seed(cfg.seed)
        projections, start_options = (
            views.projections,
            (self.normalisation, cfg.extended_object, cfg.max_atom_sigma_A),
        )
        given = start_positions(self)  # a second look's, start_atoms' or None
        # begun while the launcher loaded; the noise is read beside the candidates (either way)
        reading, from_ahead = None, cfg.init == "backprojection" and given is None
        if from_ahead and (early := self.prepared.noise(series)) is not None:
            reading = NoiseReadingBeside(projections, cfg.loss, cfg.background, early)
        ahead = self.prepared.start(series, projections, *start_options) if from_ahead else None
        if ahead is None:
            noise = measure_noise(projections)
            reading = NoiseReadingBeside(projections, cfg.loss, cfg.background, noise)
            start = compute_start(
                series,
                projections,
                *start_options,
                cfg.init == "backprojection",
                cfg.num_random,
                cfg.init_extent,
                self.generator,
                noise=noise,
                positions_A=given,
            )
        else:
            start = ahead
            reading = reading or NoiseReadingBeside(projections, cfg.loss, cfg.background, ahead.noise)
        say_series(series)
        say_start(start, ls, cfg.extended_object, ahead is not None)
        self.measured_noise = start.noise  # the views' own noise before any fit (normalised units)
        self.noise_check: dict | None = None  # the noise reading against a replica's own noise (noise_reading)
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
            length_scale=ls,
            max_log_amplitude=max_log_amp,
            generator=self.generator,
            half_extent=half_extent,
            field_half_extent=self.field_half_extent if half_extent != self.field_half_extent else None,
            **{f.name: getattr(cfg, f.name) for f in fields(DensitySettings)},  # FitOptions is a DensitySettings
        )
        self.density.reset(n)
        species_rules(self.density, series.species if series is not None else ())
        self.convergence = ConvergenceCheck(
            cfg.warmup_length,
            cfg.refine_every,
            cfg.converged_fraction,
            cfg.false_discovery_rate,
            cfg.merge_threshold_A * ls,
        )
        self.noise_read, self.data_term, floor, surfaces = say_noise_reading(reading.result(measured))
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

    def get_gaussian_param_groups(self) -> Dict[str, List[Parameter]]:
        return {name: [param] for name, param in self.gauss_params.items()}

    def get_param_groups(self) -> Dict[str, List[Parameter]]:
        """Each parameter its own group (one optimiser each, :mod:`.optimisers`)."""
        return self.get_gaussian_param_groups() | {name: [param] for name, param in self.view_params.items()}

    def load_state_dict(self, state_dict, **kwargs):  # type: ignore[override]
        """A saved fit's parameters (``gauss_params.*``, ``view_params.*``), whatever its number of
        Gaussians: the parameters are resized to the checkpoint's first."""
        n = state_dict["gauss_params.means"].shape[0]
        for name, param in self.gauss_params.items():
            self.gauss_params[name] = Parameter(torch.zeros((n,) + tuple(param.shape[1:]), device=param.device))
        self.density.reset(n)
        state_dict = with_background_terms(
            state_dict, self.view_params["background"] if "background" in self.view_params else None
        )
        return torch.nn.Module.load_state_dict(self, state_dict, **kwargs)

    # ------------------------------------------------------------------ rendering
    def get_outputs(self, camera, background: bool = True) -> Dict[str, torch.Tensor]:
        """Project the Gaussians for one ``camera`` (an :class:`~.views.OrthographicViews` of one
        view, or nerfstudio's ``Cameras``, which have the same fields; its view by the index it
        carries, :func:`~.rendering.view_of`): ``rgb`` (H, W, 3) in [0, 1] for the viewer, ``projection``
        (H, W, 1) in normalised data units (``background=False``: the view's background apart, in
        ``background``), ``depth``; with views_per_step > 1 the step's other views (``extra_projection``,
        ``extra_views``: on the model's device)."""
        if camera.shape[0] != 1:
            raise ValueError("GaussianAtomsModel renders one camera at a time")
        dev, dt = self.means.device, self.means.dtype
        c2w = camera.camera_to_worlds[0].to(dt)
        rows, cols, pitch, view = self.view_geometry.read(
            camera, c2w, self.training and self.step < self.config.coarse_steps, dev, dt
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

    # ------------------------------------------------------------------ around each step
    def step_cb(self, optimizers, step: int) -> None:
        if optimizers is not self._optimizers_obj:
            set_position_rate(self, optimizers)
        self.step, self._optimizers_obj, self.optimizers = step, optimizers, optimizers.optimizers

    def _param_lists(self):  # the optimisers' second registry of the parameters (Optimizers.parameters), kept in step
        return getattr(self._optimizers_obj, "parameters", None)

    @torch.no_grad()
    def refine_after_step(self, step: int) -> None:
        """Clamp, accumulate the positional gradient and every refine_every steps duplicate and prune."""
        if "psf" in self.view_params:
            project_weights(self.view_params["psf"].data)  # a non-negative kernel (physics/psf.py)
            self.kernel_reading.read(self, step, self.density.warmup_length, self.config.refine_every)
        self.floors.decide(self, step)  # every refine_every steps: one floor for all views, or one each
        if self.density.step_post_backward(self.gauss_params, self.optimizers, step, self._param_lists()):
            self.atoms_changed()

    @torch.no_grad()
    def merge_after_step(self, step: int) -> None:
        """The minimum-distance prior as its own callback (every merge_every steps after the warm-up)."""
        if self.density.merge_step(self.gauss_params, self.optimizers, step, self._param_lists()):
            self.atoms_changed()

    @torch.no_grad()
    def finalize(self) -> None:
        """Last merges and prune (one Gaussian per atom; the residual read by :func:`.residuals.residual_correlations`),
        then a short refit if they changed anything."""
        self.finite_watch.flush()
        read_after_fit(self)
        if (
            self.density.finalize(
                self.gauss_params, self.optimizers, self._param_lists(), lambda m, s: residual_correlations(self, m, s)
            )
            and self.optimizers
            and self.config.final_refit
        ):
            refit(self, progress=self.progress)
        self.atoms_changed()

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
        (:func:`gaussian_atoms_method.engine.results.model_position_std_A`)."""
        return model_position_std_A(self, atoms, noise)

    def converged(self, step: int) -> bool:
        """True once the atoms are settled (:func:`gaussian_atoms_method.engine.stopping.converged`)."""
        return converged(self, step)

    def write_results(self, run_dir: Path) -> dict | None:
        """atoms.xyz, atoms.csv, slices.png and evaluation.json
        (:func:`gaussian_atoms_method.engine.results.write_results`)."""
        return write_results(self, Path(run_dir))

    def write_results_at(self, last_step: int, run_dir: Path, step: int) -> None:
        """The results at the last step (not that of a reading pass)."""
        if step == last_step and not self.kernel_reading.first_pass:
            self.write_results(Path(run_dir))

    def should_stop(self, step: int, last_step: int, run_dir: Path, progress=None) -> bool:
        """At each check: True once the atoms are settled (the results written), else search,
        settle the set or slow the positions (:mod:`.stopping`); after the refine and merge, so
        judged on the atoms as they stand.  ``progress`` (a bar with ``end_at``) ends first."""
        # psf held-out: the reading ends once the kernel is held (start_again)
        if self.kernel_reading.first_pass:
            return self.kernel_reading.settled
        if not at_check(self, step, last_step):
            return False
        if look_again(self, step):  # the pass ends; start_again begins the next
            return True
        if progress is not None:  # the bar ends here, before the results print
            progress.end_at(step)
        CONSOLE.print(f"gaussian-atoms: converged at step {step}: stopping early ({self.convergence.summary()})")
        self.converged_at = step
        self.write_results(Path(run_dir))
        return True

    def snapshot_after_step(self, directory: Path, step: int) -> None:
        """Every ``snapshot_every`` steps the atoms as they stand, to ``directory`` (after step
        k*N-1, k*N steps are done)."""
        if (step + 1) % self.config.snapshot_every == 0:
            params = self.density.state.average.mean(self.gauss_params)
            in_field = self.density.in_field(params["means"]).cpu().numpy()  # the mean is detached
            stamp = time.time()  # the step's atoms are ready (the copy waited for the device)
            self.snapshots_s += write_snapshot(
                self.atoms(params),
                directory,
                step + 1,
                self.num_points,
                torch.cuda.max_memory_allocated() if self.means.is_cuda else 0,
                in_field,
                stamp,
                self.snapshots_s,
            )

    def start_again(self) -> bool:
        """After a pass that reports no atoms, set the fit up again and return True (the caller
        makes fresh optimisers); False when the run is over.  After the reading pass of ``psf
        held-out`` the kernel read is held (``psf fixed``) and the atoms start again on every view
        (Gaussians formed on half the views without the kernel keep the satellites that explained
        the probe's tails); after a second look (:mod:`.second_look`) they start from its places."""
        reading, device = getattr(self, "kernel_reading", None), self.means.device
        if reading is not None and reading.first_pass:
            self.config.psf, self.config.psf_weights = (
                "fixed",
                tuple(float(w) for w in self.view_params["psf"].detach().cpu().tolist()),
            )
            weights = ", ".join(f"{w:.3f}" for w in self.config.psf_weights)
            held = f"with the point-spread function held at {weights} (1, 2, 4 Å)"
            CONSOLE.print(f"gaussian-atoms: the atoms start again on every view {held}")
        elif getattr(self, "second_look_pending", False):
            self.second_look_pending = False
        else:
            return False
        self.setup(self.view_set)
        self.to(device)
        return True
