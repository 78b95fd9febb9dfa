"""``GaussianAtomsModel``: splatfacto with the tomographic projector in place of the rasteriser.

One isotropic Gaussian per atom.  Parameters (normalised units, see :mod:`.units`):

* ``means`` (N, 3): positions;
* ``log_sigmas`` (N, 1): one width per Gaussian, ``sigma = exp(log_sigma)`` (the isotropy
  prior); with ``isotropic=False`` (the ablation) three widths (N, 3) and a rotation ``quats``
  (N, 4), projected exactly by :func:`.projector.project_anisotropic_gaussians`;
* ``log_amplitudes`` (N, 1): the 3D peak, ``q = exp(log_amplitude)``.  The exponential keeps it
  positive and makes Adam's steps relative, so faint and bright atoms learn at the same pace.

The loss is the L1 distance between predicted and measured projections (no SSIM, no LPIPS,
no spherical harmonics, no background, no alpha).  Densification, pruning and the cluster merge
run as training callbacks registered here; the final atoms are written to the run directory.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Literal, Tuple, Type

import numpy as np
import torch
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.models.splatfacto import SplatfactoModel, SplatfactoModelConfig
from nerfstudio.utils.rich_utils import CONSOLE
from torch.nn import Parameter

from .atoms import AtomSet, read_atoms, write_atoms
from .figures import write_slices_png
from .initialise import backprojection_candidates
from .merge import cluster_labels, merged_values
from .metrics import score_atoms
from .projector import (
    covariances_from_scales_quats,
    gaussian_mass,
    project_anisotropic_gaussians,
    project_gaussians,
    project_gaussians_gsplat,
    project_gaussians_tiled,
    typical_mass,
)
from .remap import apply_remap, duplicate_remap, keep_remap, merge_remap
from .uncertainty import position_std_A, robust_noise_std
from .units import DATA_RANGE, Normalisation
from .viewer import AtomsInViewer, mass_colours



@dataclass
class GaussianAtomsModelConfig(SplatfactoModelConfig):
    """Gaussian atoms: isotropic 3D Gaussians fitted to a tilt series."""

    _target: Type = field(default_factory=lambda: GaussianAtomsModel)
    init: Literal["backprojection", "random"] = "backprojection"
    """Where the Gaussians start: at the strongest local maxima of a smoothed filtered
    back-projection (see :mod:`gaussian_atoms_method.initialise`), or at random positions (the
    paper).  Back-projection needs single-axis tilts; otherwise random is used."""
    init_mass: Literal["backprojection", "equal"] = "backprojection"
    """How the measured mass is shared among the starting Gaussians: in proportion to the
    smoothed back-projection at each (noise candidates start faint and are pruned sooner;
    back-projection start only), or equally."""
    num_random: int = 10000
    """Number of Gaussians to start from (at most this many back-projection candidates)."""
    init_sigma_A: float = 0.7
    """Initial width of every Gaussian, Å."""
    init_extent: float = 0.8
    """Side of the cube (normalised units, the detector's longer side is 1) that the random
    Gaussians start in."""
    min_sigma_A: float = 0.15
    """Floor on the width, Å: no atom (after probe blur) is narrower; keeps the fit finite."""
    max_atom_sigma_A: float = 1.5
    """Gaussians wider than this (Å) are not atoms (an atom blurred by a 0.5 Å probe is about
    0.6 Å wide): they are pruned and left out of the typical atom mass."""
    max_sigma_A: float = 5.0
    """Ceiling on the width, Å: far wider than any atom; keeps a runaway Gaussian finite."""
    warmup_length: int = 200
    """Steps before the first densify / prune / merge."""
    refine_every: int = 100
    """Steps between densify / prune / merge."""
    stop_split_at: int = 2500
    """No more duplication after this step (pruning and merging continue)."""
    densify_grad_thresh: float = 0.2
    """Duplicate Gaussians whose mean positional gradient (norm of the average gradient vector
    over a refine interval, normalised units) exceeds this.  Measured on the demo data, a
    fitted atom's sits at 0.02-0.1 (L1 noise), so 0.2 only duplicates under a persistent pull.
    The paper's 0.005 is on gsplat's screen-space scale and would duplicate everything here."""
    max_gaussians: int = 200000
    """Never hold more Gaussians than this."""
    prune_mass_fraction: float = 0.25
    """Prune Gaussians whose integrated mass is below this fraction of a typical atom's
    (the mass-weighted median mass)."""
    isotropic: bool = True
    """One width per Gaussian (the isotropy prior).  False: three widths and a rotation each."""
    cluster_merge: bool = True
    """Merge Gaussians closer than merge_threshold_A (the minimum-distance prior)."""
    merge_every: int = 100
    """Steps between cluster merges (after the warm-up)."""
    merge_threshold_A: float = 0.7
    """Gaussians closer than this (Å) merge into one."""
    merge_amplitude: Literal["mass", "mean"] = "mass"
    """Amplitude of a merged Gaussian: conserve the summed mass, or the mean amplitude (paper)."""
    projector: Literal["auto", "tiled", "dense", "gsplat"] = "auto"
    """Projection backend (all exact to float32; docs/performance.md): ``dense``, the full-image
    separable matmul (fastest on a GPU: 1.4-3 ms per 280x280 view for 1k-50k Gaussians on an
    H100); ``tiled``, each Gaussian only on the tiles it reaches (about 4x faster than dense on
    a CPU); ``gsplat``, tiled with stock gsplat's tile intersection (CUDA only; correct but
    slower than dense at these sizes).  ``auto``: dense on CUDA, tiled on CPU."""
    loss: Literal["l1", "l2"] = "l1"
    """Data term: L1 (the paper; robust to outliers) or L2 (unbiased for the mean: better at
    low electron counts, where the median of a Poisson count sits below its mean and L1 lets
    faint atoms fade; measured on the aSi-208 data at dose 1.6e4)."""
    background: Literal["none", "constant", "plane"] = "none"
    """A smooth per-projection background learned with the atoms (carbon support, contamination,
    a detector offset): a constant, or a plane over the detector, per view."""
    refine_alignment: bool = False
    """Learn a per-projection in-plane shift with the atoms (residual misalignment of the tilt
    series).  Shifts are taken relative to their mean over the views (an overall shift of
    every view is the same as moving the particle)."""
    coarse_steps: int = 300
    """Coarse to fine: the first this many steps fit the projections binned 2 x 2 (a quarter of
    the pixels to evaluate), then full resolution.  0: always full resolution.  300 covers the
    warm-up and the first prune, where the atoms are found and the noise candidates go: on the
    Au particle that reaches the accuracy targets 7-9 s sooner on a CPU with the same final
    result (docs/performance.md, skips)."""
    stop_when_converged: bool = True
    """End training early once the atoms are settled: the Gaussian count unchanged and the RMS
    step of the positions over a refine interval below ``converged_fraction`` of the atoms'
    noise-limited precision (:mod:`gaussian_atoms_method.uncertainty`) at two checks in a row.
    Further steps would move the atoms by less than the data can tell apart."""
    converged_fraction: float = 1.0
    """See stop_when_converged."""
    refine_tilts: bool = False
    """Learn a per-projection tilt-angle offset (about the tilt axis) with the atoms: errors of
    the goniometer readings.  Offsets are taken relative to their mean (a common offset is the
    same as rotating the particle).  Single-axis tilt series only."""
    views_per_step: int = 1
    """Training views fitted per step: the view nerfstudio hands the model and this many minus
    one others drawn at random, rendered in one projector call, one loss over all.  On a GPU a
    batch of views costs about one view's kernel launches and the averaged gradient is smoother
    (docs/performance.md: several views per step); on a CPU each view costs its own time.  Not
    with refine-alignment, refine-tilts, background or anisotropic Gaussians."""
    snapshot_every: int = 0
    """Every this many steps (0: never) write the current atoms to ``snapshots/`` in the run
    directory with the wall-clock time, for time-to-accuracy benchmarks."""
    seed: int = 0
    """Seed of the random initialisation and duplications."""


def _detector_axes(c2w: torch.Tensor) -> torch.Tensor:
    """(..., 2, 3) world directions of the detector rows and columns of nerfstudio camera
    poses (..., 3, 4): columns along the camera's x, rows down its y."""
    return torch.stack([-c2w[..., :, 1], c2w[..., :, 0]], dim=-2)


def _binned_like(image: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """(H, W, C) ``image`` as is, or averaged over 2 x 2 blocks to the (H/2, W/2) of ``like``."""
    h, w = like.shape[:2]
    if image.shape[:2] != (h, w):
        image = image[: 2 * h, : 2 * w].reshape(h, 2, w, 2, -1).mean(dim=(1, 3))
    return image


class GaussianAtomsModel(SplatfactoModel):
    """Splatfacto subclass whose renderer is the tomographic line-integral projector."""

    config: GaussianAtomsModelConfig

    # ------------------------------------------------------------------ set-up
    def populate_modules(self) -> None:
        # Deliberately not splatfacto's: that builds LPIPS (downloads weights), SH colours,
        # opacities and gsplat's alpha-compositing strategy, none of which apply here.
        cfg = self.config
        metadata = self.kwargs.get("metadata", {}) or {}
        self.normalisation: Normalisation = metadata.get("normalisation") or Normalisation(1.0, 1.0)
        truth = metadata.get("truth_path")
        self.truth_path: Path | None = Path(truth) if truth is not None else None
        self.generator = torch.Generator().manual_seed(cfg.seed)
        means, weights = self._initial_means(metadata.get("tilt_series"))
        n = means.shape[0]
        sigma0 = cfg.init_sigma_A * self.normalisation.length_scale
        log_sigmas = torch.full((n, 1 if cfg.isotropic else 3), math.log(sigma0))
        amp0 = self._initial_amplitude(metadata, n, sigma0)
        log_amps = torch.full((n, 1), math.log(amp0))
        if weights is not None and cfg.init_mass == "backprojection":
            log_amps += torch.log(weights)[:, None]
        # Every Gaussian's mass stays below 1000x the whole measured mass (see clamp_parameters).
        floor_sigma = cfg.min_sigma_A * self.normalisation.length_scale
        self._max_log_amplitude = math.log(1000.0 * max(n, 1) * amp0 * (sigma0 / floor_sigma) ** 3)
        params = {"means": Parameter(means), "log_sigmas": Parameter(log_sigmas), "log_amplitudes": Parameter(log_amps)}
        if not cfg.isotropic:
            # Near-identity rotations; exactly identity would start every ellipsoid axis-aligned.
            quats = torch.tensor([1.0, 0.0, 0.0, 0.0]) + 0.1 * torch.randn(n, 4, generator=self.generator)
            params["quats"] = Parameter(quats)
        self.gauss_params = torch.nn.ParameterDict(params)
        # Per-view parameters (not per-Gaussian: untouched by densify / prune / merge).
        view_c2w = metadata.get("view_c2w")
        self.register_buffer("view_c2w", view_c2w.float() if view_c2w is not None else torch.zeros(0, 3, 4), persistent=False)
        n_views = self.view_c2w.shape[0]
        view_params = {}
        if cfg.background != "none":
            view_params["background"] = Parameter(torch.zeros(n_views, 1 if cfg.background == "constant" else 3))
        if cfg.refine_alignment:
            view_params["view_shifts"] = Parameter(torch.zeros(n_views, 2))
        if cfg.refine_tilts:
            series = metadata.get("tilt_series")
            if series is None:
                raise ValueError("--pipeline.model.refine-tilts needs a single-axis tilt series from the tilt-series dataparser")
            view_params["view_tilts"] = Parameter(torch.zeros(n_views, 1))
            axis = torch.tensor([0.0, 1.0, 0.0] if series.tilt_axis == "y" else [1.0, 0.0, 0.0])
            self.register_buffer("tilt_axis_vector", axis, persistent=False)
        self.view_params = torch.nn.ParameterDict(view_params)
        self.step = 0
        self.optimizers: Dict[str, torch.optim.Optimizer] = {}
        self._optimizers_obj = None
        self._grad_accum = torch.zeros(n, 3)
        self._grad_count = 0
        self.crop_box = None
        self.background_color = torch.zeros(3)
        # Draws the atoms as points in nerfstudio's viewer (found there as a ViewerControl).
        self.atoms_in_viewer = AtomsInViewer(self._viewer_atoms)
        self._setup_view_batches(metadata)

    @torch.no_grad()
    def _viewer_atoms(self) -> tuple[np.ndarray, np.ndarray, float]:
        """Positions (world units), integrated masses and a point size (the median width)."""
        sigmas = self.sigmas.detach().cpu()
        masses = gaussian_mass(sigmas, self.amplitudes.detach().cpu())
        size = float(sigmas.median()) if len(sigmas) else 0.01
        return self.means.detach().cpu().numpy(), masses.numpy(), size

    def _initial_means(self, series) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(n, 3) starting positions in normalised units, and for a back-projection start (n,)
        weights of mean 1 in proportion to the smoothed back-projection there (else None)."""
        cfg = self.config
        if cfg.init == "backprojection" and series is not None:
            # The model is built on the CPU and moved afterwards; a GPU, if there is one, does
            # the back-projection.
            positions_A, values = backprojection_candidates(
                series.projections, series.angles_deg, series.pixel_size_A, series.tilt_axis, series.centre_px, cfg.num_random,
                device="cuda" if torch.cuda.is_available() else "cpu", return_values=True,
            )  # fmt: skip
            if len(positions_A):
                CONSOLE.print(f"gaussian-atoms: {len(positions_A)} Gaussians start at back-projection maxima")
                # A candidate made of noise reads about zero; a floor of 1% of the strongest
                # keeps every weight positive (a log-amplitude) without making it atom-like.
                values = torch.as_tensor(values, dtype=torch.float64)
                values = values.clamp_min(0.01 * float(values.max().clamp_min(1e-30)))
                return torch.as_tensor(positions_A * self.normalisation.length_scale, dtype=torch.float32), (values / values.mean()).float()
        return (torch.rand(cfg.num_random, 3, generator=self.generator) - 0.5) * cfg.init_extent, None

    @staticmethod
    def _initial_amplitude(metadata: dict, n: int, sigma: float) -> float:
        """3D peak (normalised units) that shares the measured mass equally among ``n`` Gaussians
        of width ``sigma``: every Gaussian starts atom-like in total, and the fit sorts them."""
        projections = metadata.get("projections")
        pixel_size_A = metadata.get("pixel_size_A")
        norm = metadata.get("normalisation")
        if projections is None or pixel_size_A is None or norm is None:
            # No data to size them by: a faint fraction of an atom-sized projected peak.
            return 0.05 * DATA_RANGE / (sigma * math.sqrt(2 * math.pi))
        pixel_area = (pixel_size_A * norm.length_scale) ** 2
        mass = float(projections.double().sum(dim=(-2, -1)).mean().clamp_min(0.0)) * pixel_area
        mass_each = max(mass, 1e-12) / max(n, 1)
        return mass_each / (2 * math.pi * sigma**2) ** 1.5

    # ------------------------------------------------------------------ parameters
    @property
    def means(self) -> torch.Tensor:
        return self.gauss_params["means"]

    @property
    def sigmas(self) -> torch.Tensor:
        """(N,) widths; without isotropy the geometric mean of the three (same volume, same mass)."""
        return torch.exp(self._log_scales().mean(dim=-1))

    def _log_scales(self) -> torch.Tensor:
        floor = math.log(self.config.min_sigma_A * self.normalisation.length_scale)
        return self.gauss_params["log_sigmas"].clamp_min(floor)

    @property
    def amplitudes(self) -> torch.Tensor:
        return torch.exp(self.gauss_params["log_amplitudes"]).squeeze(-1)

    @property
    def num_points(self) -> int:
        return self.means.shape[0]

    # splatfacto's other per-Gaussian properties, in our terms (the viewer reads every property
    # of the model when it starts; splatfacto's would look up parameters we do not have).
    @property
    def scales(self) -> torch.Tensor:
        """(N, 3) log-widths, as splatfacto stores them."""
        return self._log_scales().expand(-1, 3)

    @property
    def quats(self) -> torch.Tensor:
        """(N, 4) rotations (identity for isotropic Gaussians)."""
        if "quats" in self.gauss_params:
            return self.gauss_params["quats"]
        return torch.tensor([1.0, 0.0, 0.0, 0.0], device=self.means.device).expand(self.num_points, 4)

    @property
    def opacities(self) -> torch.Tensor:
        """(N, 1) log-amplitudes: the nearest thing to an opacity (nothing is composited)."""
        return self.gauss_params["log_amplitudes"]

    @property
    def colors(self) -> torch.Tensor:
        """(N, 3) colours in [0, 1] by integrated mass (as the viewer's point cloud)."""
        _, masses, _ = self._viewer_atoms()
        return torch.as_tensor(mass_colours(masses) / 255.0, dtype=torch.float32)

    @property
    def features_dc(self) -> torch.Tensor:
        return self.colors

    @property
    def features_rest(self) -> torch.Tensor:
        return torch.zeros(self.num_points, 0, 3)

    @property
    def shs_0(self) -> torch.Tensor:
        return self.colors[:, None, :]

    @property
    def shs_rest(self) -> torch.Tensor:
        return self.features_rest

    def load_state_dict(self, state_dict, **kwargs):  # type: ignore[override]
        # Resize the parameters to the checkpoint's number of Gaussians before loading.
        n = state_dict["gauss_params.means"].shape[0]
        for name, param in self.gauss_params.items():
            self.gauss_params[name] = Parameter(torch.zeros((n,) + tuple(param.shape[1:]), device=param.device))
        self._grad_accum = torch.zeros(n, 3)
        return torch.nn.Module.load_state_dict(self, state_dict, **kwargs)

    def get_gaussian_param_groups(self) -> Dict[str, List[Parameter]]:
        return {name: [param] for name, param in self.gauss_params.items()}

    def get_param_groups(self) -> Dict[str, List[Parameter]]:
        return self.get_gaussian_param_groups() | {name: [param] for name, param in self.view_params.items()}

    def projector_name(self, device: torch.device) -> str:
        """The projector ``projector`` names on ``device`` ("auto": dense on CUDA, else tiled)."""
        choice = self.config.projector
        if choice == "auto":
            choice = "dense" if device.type == "cuda" else "tiled"
        return choice

    def _projector(self, device: torch.device):
        choice = self.projector_name(device)
        if choice == "gsplat" and device.type != "cuda":
            raise ValueError("--pipeline.model.projector gsplat needs a CUDA device; use auto, tiled or dense on CPU")
        return {"dense": project_gaussians, "tiled": project_gaussians_tiled, "gsplat": project_gaussians_gsplat}[choice]

    def view_index(self, camera: Cameras) -> int | None:
        """Index of the training view this camera is (by its pose), or None for another view."""
        if self.view_c2w.shape[0] == 0:
            return None
        c2w = camera.camera_to_worlds[0].to(self.view_c2w)
        dist = (self.view_c2w - c2w).abs().flatten(1).max(dim=1).values
        best = int(torch.argmin(dist))
        return best if float(dist[best]) < 1e-5 else None

    def _setup_view_batches(self, metadata: dict) -> None:
        """With views_per_step > 1 the model holds the measured projections (the loss of the
        extra views needs them) and checks the views can share one projector call."""
        cfg = self.config
        if cfg.views_per_step < 1:
            raise ValueError(f"--pipeline.model.views-per-step must be at least 1, got {cfg.views_per_step}")
        self.register_buffer("train_projections", torch.zeros(0, 1, 1), persistent=False)
        if cfg.views_per_step == 1:
            return
        unsupported = [name for name, on in (("refine-alignment", cfg.refine_alignment), ("refine-tilts", cfg.refine_tilts),
                       ("background", cfg.background != "none"), ("isotropic False", not cfg.isotropic)) if on]  # fmt: skip
        if unsupported:
            raise ValueError(f"--pipeline.model.views-per-step {cfg.views_per_step} cannot be combined with --pipeline.model.{unsupported[0]} (per-view parameters); use 1")
        projections = metadata.get("projections")
        if projections is None or self.view_c2w.shape[0] < 2:
            raise ValueError("--pipeline.model.views-per-step > 1 needs a tilt series from the tilt-series dataparser (its projections and view poses)")
        # One call projects the same means for every view: each camera must sit on its beam
        # axis through the tilt centre (true of the dataparser's cameras).
        c2w = self.view_c2w
        off_axis = torch.stack([(c2w[:, :, 3] * c2w[:, :, 0]).sum(-1), (c2w[:, :, 3] * c2w[:, :, 1]).sum(-1)]).abs().max()
        if float(off_axis) > 1e-5:
            raise ValueError("--pipeline.model.views-per-step > 1 needs every camera on its beam axis through the tilt centre")
        self.train_projections = torch.as_tensor(projections, dtype=torch.float32)

    def _other_views(self, view: int) -> torch.Tensor:
        """views_per_step - 1 distinct training views other than ``view``, drawn at random."""
        n = self.view_c2w.shape[0]
        k = min(self.config.views_per_step - 1, n - 1)
        others = torch.randperm(n - 1, generator=self.generator)[:k]
        return others + (others >= view).long()  # skip ``view`` itself

    # ------------------------------------------------------------------ rendering
    def get_outputs(self, camera: Cameras) -> Dict[str, torch.Tensor]:
        """Project the Gaussians for one orthographic camera.

        Returns ``projection`` (H, W, 1) in normalised data units and ``rgb`` (H, W, 3), the
        same scaled to [0, 1] for the viewer.
        """
        if camera.shape[0] != 1:
            raise ValueError("GaussianAtomsModel renders one camera at a time")
        c2w = camera.camera_to_worlds[0].to(self.means.dtype)
        (rows_dir, cols_dir), t = _detector_axes(c2w), c2w[:, 3]
        h, w = int(camera.height.item()), int(camera.width.item())
        dev, dt = self.means.device, self.means.dtype
        row_coords = (torch.arange(h, device=dev, dtype=dt) + 0.5 - camera.cy[0, 0].to(dt)) / camera.fy[0, 0].to(dt)
        col_coords = (torch.arange(w, device=dev, dtype=dt) + 0.5 - camera.cx[0, 0].to(dt)) / camera.fx[0, 0].to(dt)
        if int(camera.camera_type[0, 0]) != CameraType.ORTHOPHOTO.value:
            # A perspective camera (the viewer's): project along its view direction with the
            # magnification it has at the tilt centre, so zooming in and out works as expected.
            distance = torch.dot(t, c2w[:, 2]).clamp_min(1e-3)
            row_coords, col_coords = row_coords * distance, col_coords * distance
        if self.training and self.step < self.config.coarse_steps:
            # Coarse phase: the centres of 2 x 2 pixel blocks (the loss bins the data alike).
            h, w = h // 2, w // 2
            row_coords = row_coords[: 2 * h].view(h, 2).mean(dim=1)
            col_coords = col_coords[: 2 * w].view(w, 2).mean(dim=1)
        batching = self.training and self.config.views_per_step > 1
        view = self.view_index(camera) if len(self.view_params) or batching else None
        batching = batching and view is not None
        if view is not None and "view_tilts" in self.view_params:
            # The view was taken at its nominal angle plus an error: rotate its detector axes
            # about the tilt axis by that error (Rodrigues' formula).
            tilts = self.view_params["view_tilts"]
            delta = (tilts[view, 0] - tilts[:, 0].mean()).to(dt)
            a = self.tilt_axis_vector.to(dev, dt)
            rotate = lambda v: v * torch.cos(delta) + torch.linalg.cross(a, v) * torch.sin(delta) + a * torch.dot(a, v) * (1 - torch.cos(delta))  # noqa: E731
            # The whole camera turns about the tilt axis through the tilt centre (its position
            # too: otherwise its offset along the beam would leak into the image as a shift).
            rows_dir, cols_dir, t = rotate(rows_dir), rotate(cols_dir), rotate(t)
        axes = torch.stack([rows_dir, cols_dir])[None]
        if view is not None and "view_shifts" in self.view_params:
            # The view's content sits shifted by s: evaluate the ideal projection at x - s.
            shifts = self.view_params["view_shifts"]
            s = (shifts[view] - shifts.mean(dim=0)).to(dt)
            row_coords, col_coords = row_coords - s[0], col_coords - s[1]
        extra = {}
        if batching:
            # This view and the others in one call (cameras sit on their beam axes through the
            # tilt centre, so the means need no per-view offset).
            others = self._other_views(view)
            axes = torch.cat([axes, _detector_axes(self.view_c2w[others].to(dev, dt))])
            images = self._projector(dev)(self.means, self.sigmas, self.amplitudes, axes, row_coords, col_coords)
            image, extra = images[0], {"extra_projection": images[1:, :, :, None], "extra_views": others}
        elif self.config.isotropic:
            project = self._projector(dev)
            image = project(self.means - t, self.sigmas, self.amplitudes, axes, row_coords, col_coords)[0]
        else:
            cov = covariances_from_scales_quats(self._log_scales(), self.gauss_params["quats"])
            image = project_anisotropic_gaussians(self.means - t, cov, self.amplitudes, axes, row_coords, col_coords)[0]
        if view is not None and "background" in self.view_params:
            c = self.view_params["background"][view].to(dt)
            image = image + c[0]
            if len(c) == 3:  # plane over the detector, in normalised coordinates
                image = image + c[1] * row_coords[:, None] + c[2] * col_coords[None, :]
        projection = image[..., None]
        rgb = (projection / DATA_RANGE).clamp(0.0, 1.0).expand(h, w, 3)
        # A line integral has no depth; the viewer needs one to composite its scene (the atom
        # points, the camera frustums) with our image: put the image behind everything.
        depth = torch.full((1, 1, 1), 1e3, device=dev, dtype=dt).expand(h, w, 1)
        return {"rgb": rgb, "projection": projection, "depth": depth, **extra}  # rgb first: the viewer shows it

    # ------------------------------------------------------------------ losses and metrics
    @staticmethod
    def _measured(outputs, batch) -> torch.Tensor:
        """The measured projection, binned 2 x 2 when the rendering is (coarse phase)."""
        return _binned_like(batch["image"].to(outputs["projection"]), outputs["projection"])

    def get_metrics_dict(self, outputs, batch) -> Dict[str, torch.Tensor]:
        gt = self._measured(outputs, batch)
        return {"l1": torch.abs(outputs["projection"] - gt).mean().detach(), "gaussian_count": torch.tensor(float(self.num_points))}

    def get_loss_dict(self, outputs, batch, metrics_dict=None) -> Dict[str, torch.Tensor]:
        gt = self._measured(outputs, batch)
        residual = outputs["projection"] - gt
        if "extra_projection" in outputs:
            # The other views of this step: one loss over all the pixels of all of them.
            extra = outputs["extra_projection"]
            extra_gt = torch.stack([_binned_like(m[..., None], extra[0]) for m in self.train_projections[outputs["extra_views"]]])
            residual = torch.cat([residual[None], extra - extra_gt.to(extra)])
        loss = torch.abs(residual).mean() if self.config.loss == "l1" else residual.square().mean()
        # Parameters are checked too: the tiled projector skips a Gaussian whose centre is NaN
        # (its window is empty), which would otherwise go unnoticed.
        if not torch.isfinite(loss) or not all(bool(torch.isfinite(p).all()) for p in self.gauss_params.values()):
            raise FloatingPointError(self._divergence_message(loss, gt))
        return {"main_loss": loss}

    def _divergence_message(self, loss: torch.Tensor, gt: torch.Tensor) -> str:
        """Name the step and the cause of a non-finite loss (training stops instead of going on
        with NaN)."""
        bad = {name: int((~torch.isfinite(p)).any(dim=-1).sum()) for name, p in self.gauss_params.items()}
        bad = {k: v for k, v in bad.items() if v}
        if bad:
            cause = ", ".join(f"{v} Gaussian(s) with non-finite {k}" for k, v in bad.items())
        elif not torch.isfinite(gt).all():
            cause = "the measured projection holds NaN/Inf"
        else:
            cause = "the projection overflowed (amplitudes too large for float32?)"
        return f"gaussian-atoms: step {self.step}: the loss is {float(loss)} and training cannot go on; cause: {cause}. Lower the learning rates or check the input."

    def get_image_metrics_and_images(self, outputs, batch) -> Tuple[Dict[str, float], Dict[str, torch.Tensor]]:
        gt = batch["image"].to(outputs["projection"])
        pred = outputs["projection"]
        mse = torch.mean((pred - gt) ** 2)
        metrics = {
            "l1": float(torch.abs(pred - gt).mean()),
            "psnr": float(10 * torch.log10(DATA_RANGE**2 / mse.clamp_min(1e-12))),
            "gaussian_count": float(self.num_points),
        }
        both = torch.cat([gt, pred], dim=1) / DATA_RANGE
        return metrics, {"img": both.clamp(0, 1).expand(-1, -1, 3)}

    # ------------------------------------------------------------------ training callbacks
    def get_training_callbacks(self, training_callback_attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
        attrs = training_callback_attributes
        cbs = [
            TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], self.step_cb, args=[attrs.optimizers]),
            TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self.refine_after_step),
        ]
        if self.config.cluster_merge:
            cbs.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self.merge_after_step))
        trainer = attrs.trainer
        if trainer is not None:
            last = trainer._start_step + trainer.config.max_num_iterations - 1
            cbs.append(
                TrainingCallback(
                    [TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self._write_results_at, args=[last, trainer.base_dir]
                )
            )
            # After the refine and merge callbacks: judged on the atoms as they stand.
            cbs.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self._stop_if_converged, args=[trainer, last]))
            if self.config.snapshot_every > 0:
                cbs.append(
                    TrainingCallback(
                        [TrainingCallbackLocation.AFTER_TRAIN_ITERATION],
                        self._snapshot_after_step,
                        args=[Path(trainer.base_dir) / "snapshots"],
                    )
                )
        return cbs

    def step_cb(self, optimizers, step: int) -> None:
        self.step = step
        self._optimizers_obj = optimizers
        self.optimizers = optimizers.optimizers

    @torch.no_grad()
    def refine_after_step(self, step: int) -> None:
        """Keep the parameters in their physical range; accumulate positional gradients; every
        refine_every steps densify and prune."""
        self.clamp_parameters()
        grad = self.gauss_params["means"].grad
        if grad is not None:
            # Sum the gradient vectors, not their norms: with an L1 loss the per-step gradient of a
            # well-fitted Gaussian is noise that cancels, a persistent pull towards unexplained
            # signal does not.
            self._grad_accum += grad.detach().cpu()
            self._grad_count += 1
        cfg = self.config
        if step < cfg.warmup_length or step % cfg.refine_every != 0:
            return
        if step < cfg.stop_split_at:
            self.densify()
        self.prune()
        self._grad_accum = torch.zeros(self.num_points, 3)
        self._grad_count = 0
        self.atoms_in_viewer.refresh()

    @torch.no_grad()
    def merge_after_step(self, step: int) -> None:
        """The minimum-distance prior as its own callback: every ``merge_every`` steps after the
        warm-up, merge the clusters of Gaussians closer than ``merge_threshold_A``."""
        cfg = self.config
        if step >= cfg.warmup_length and step % cfg.merge_every == 0:
            self.merge()
            self.atoms_in_viewer.refresh()

    @torch.no_grad()
    def clamp_parameters(self) -> None:
        """Widths within [min_sigma_A, max_sigma_A]; amplitudes below a mass of 1000 times all
        the measured signal; positions within twice the volume.  Far outside what an atom can
        be, these bounds only stop a runaway Gaussian from overflowing float32."""
        ls = self.normalisation.length_scale
        self.gauss_params["log_sigmas"].data.clamp_(math.log(self.config.min_sigma_A * ls), math.log(self.config.max_sigma_A * ls))
        self.gauss_params["log_amplitudes"].data.clamp_(max=self._max_log_amplitude)
        self.gauss_params["means"].data.clamp_(-1.0, 1.0)

    def _remap(self, src, dst, n_out, new_values=None) -> None:
        dev = self.means.device
        lists = getattr(self._optimizers_obj, "parameters", None)
        apply_remap(self.gauss_params, self.optimizers, src.to(dev), dst.to(dev), n_out, new_values, lists)
        # The accumulated gradients follow their Gaussians (merged ones sum their pulls).
        accum = torch.zeros(n_out, 3)
        self._grad_accum = accum.index_add_(0, dst.cpu(), self._grad_accum[src.cpu()])

    def densify(self) -> int:
        """Duplicate Gaussians with a high mean positional gradient; each copy takes half the mass."""
        if self._grad_count == 0:
            return 0
        mean_grad = (self._grad_accum / self._grad_count).norm(dim=-1)
        idx = torch.nonzero(mean_grad > self.config.densify_grad_thresh).flatten()
        room = self.config.max_gaussians - self.num_points
        if room <= 0 or len(idx) == 0:
            return 0
        idx = idx[torch.argsort(mean_grad[idx], descending=True)[:room]]
        n = self.num_points
        self._remap(*duplicate_remap(n, idx))
        # Halve both amplitudes and move the pair apart by one sigma in a random direction.
        dev = self.means.device
        both = torch.cat([idx, torch.arange(n, n + len(idx))]).to(dev)
        self.gauss_params["log_amplitudes"].data[both] -= math.log(2.0)
        direction = torch.randn(len(idx), 3, generator=self.generator).to(dev)
        direction = direction / direction.norm(dim=-1, keepdim=True)
        offset = 0.5 * direction * self.sigmas[idx.to(dev), None]
        self.gauss_params["means"].data[idx.to(dev)] += offset
        self.gauss_params["means"].data[n:] -= offset
        return len(idx)

    @torch.no_grad()
    def typical_atom_mass(self) -> float:
        """Mass-weighted median of the Gaussians' integrated masses: a typical atom's mass.

        Half of the total mass sits in Gaussians at least this heavy.  Faint leftovers may
        outnumber the atoms but carry little of the mass, so unlike a plain median this stays
        on the atoms.  Only atom-like widths (<= max_atom_sigma_A) count: on the aSi-208 data
        a Gaussian of 10 Å width grew to absorb the projections' constant background, held
        most of the mass, and the prune then removed every atom.
        """
        atom_like = self.sigmas <= self.config.max_atom_sigma_A * self.normalisation.length_scale
        return typical_mass(gaussian_mass(self.sigmas, self.amplitudes)[atom_like])

    def prune(self) -> int:
        """Remove Gaussians too faint or too wide to be an atom, or outside the reconstruction volume."""
        mass = gaussian_mass(self.sigmas, self.amplitudes)
        keep = mass >= self.config.prune_mass_fraction * self.typical_atom_mass()
        keep &= self.sigmas <= self.config.max_atom_sigma_A * self.normalisation.length_scale
        keep &= (self.means.abs() <= 0.5).all(dim=-1)
        removed = int((~keep).sum())
        if removed:
            self._remap(*keep_remap(keep.cpu()))
        return removed

    def merge(self) -> int:
        """Replace every cluster of Gaussians closer than merge_threshold_A by one."""
        thr = self.config.merge_threshold_A * self.normalisation.length_scale
        labels, n_clusters = cluster_labels(self.means.detach().cpu().numpy(), thr)
        n = self.num_points
        if n_clusters == n:
            return 0
        labels_t = torch.as_tensor(labels, device=self.means.device)
        means, sigmas, amps = merged_values(self.means, self.sigmas, self.amplitudes, labels_t, n_clusters, self.config.merge_amplitude)
        new_values = {"means": means, "log_amplitudes": torch.log(amps)[:, None]}
        if self.config.isotropic:
            new_values["log_sigmas"] = torch.log(sigmas)[:, None]
        # Without isotropy the three log-widths (and rotations) take their cluster's mean.
        self._remap(*merge_remap(labels_t.cpu(), n_clusters), new_values)
        return n - n_clusters

    # ------------------------------------------------------------------ results
    @torch.no_grad()
    def atoms(self) -> AtomSet:
        """The current Gaussians as atoms in Å, in the frame of the input's truth file."""
        norm = self.normalisation
        return AtomSet(
            positions=norm.positions_to_A(self.means.detach().cpu().double().numpy()),
            sigmas=norm.sigmas_to_A(self.sigmas.detach().cpu().double().numpy()),
            amplitudes=norm.amplitudes_to_physical(self.amplitudes.detach().cpu().double().numpy()),
        )

    @torch.no_grad()
    def finalize(self) -> None:
        """Last merge and prune so the result holds one Gaussian per atom."""
        if self.config.cluster_merge:
            self.merge()
        self.prune()
        self.atoms_in_viewer.refresh()

    def _snapshot_after_step(self, directory: Path, step: int) -> None:
        # Steps count from 0: after step k*N-1, k*N steps are done (the last is the final result).
        if (step + 1) % self.config.snapshot_every == 0:
            self.write_snapshot(directory, step + 1)

    @torch.no_grad()
    def write_snapshot(self, directory: Path, step: int) -> None:
        """The atoms as they stand after ``step`` steps (after that step's prune and merge) and
        the wall-clock time: ``step-NNNNNN.csv`` and a line ``step,unix_time,gaussians,peak_gpu_bytes`` in ``times.csv``."""
        directory.mkdir(parents=True, exist_ok=True)
        write_atoms(self.atoms(), directory / f"step-{step:06d}.csv")
        gpu = torch.cuda.max_memory_allocated() if self.means.is_cuda else 0
        with open(directory / "times.csv", "a") as f:
            f.write(f"{step},{time.time():.3f},{self.num_points},{gpu}\n")

    def _write_results_at(self, last_step: int, run_dir: Path, step: int) -> None:
        if step == last_step:
            self.write_results(Path(run_dir))

    @torch.no_grad()
    def converged(self, step: int) -> bool:
        """True once the atoms are settled (see ``stop_when_converged``); checked after each
        refine interval's densify / prune / merge."""
        cfg = self.config
        if step < cfg.warmup_length or step % cfg.refine_every != 0:
            return False
        positions = self.means.detach().cpu().clone()
        previous, self._previous_positions = getattr(self, "_previous_positions", None), positions
        if previous is None or previous.shape != positions.shape:
            self._settled_checks = 0
            return False
        step_A = float((positions - previous).square().sum(dim=1).mean().sqrt()) / self.normalisation.length_scale
        # The pixel noise is estimated from the residuals at the first check, then kept.
        precision = self.position_std_A(self.atoms(), getattr(self, "_noise_std", None))
        if precision is None:
            return False
        std, self._noise_std = precision
        precision_A = float(np.median(np.sqrt((std**2).sum(axis=1))))
        self._settled_checks = self._settled_checks + 1 if step_A < cfg.converged_fraction * precision_A else 0
        return self._settled_checks >= 2

    def _stop_if_converged(self, trainer, last_step: int, step: int) -> None:
        if self.config.stop_when_converged and step < last_step and self.converged(step):
            CONSOLE.print(f"gaussian-atoms: converged at step {step}: stopping early")
            self.write_results(Path(trainer.base_dir))
            trainer.stop_training = True  # nerfstudio's loop ends before the next step

    @torch.no_grad()
    def position_std_A(self, atoms: AtomSet, noise: float | None = None) -> tuple[np.ndarray, float] | None:
        """Each atom's position precision (N, 3) in Å and the pixel noise it assumes (input
        units; estimated from the residuals of the training views unless given)
        (:mod:`.uncertainty`); None without the tilt series (a model built outside the
        dataparser)."""
        metadata = self.kwargs.get("metadata", {}) or {}
        series, projections = metadata.get("tilt_series"), metadata.get("projections")
        if series is None or projections is None or len(atoms) == 0:
            return None
        if noise is None:
            from dataparsers.tilt_series_dataparser import cameras_from_tilt_series

            cameras = cameras_from_tilt_series(series, self.normalisation).to(self.means.device)
            training = self.training
            self.eval()  # full resolution, one view each, whatever the phase
            try:
                residuals = [
                    (self.get_outputs(cameras[i : i + 1])["projection"][..., 0].cpu() - projections[i]).numpy() for i in range(len(cameras))
                ]
            finally:
                self.train(training)
            noise = robust_noise_std(np.stack(residuals)) / self.normalisation.data_scale
        axes = _detector_axes(self.view_c2w.cpu().double()).numpy()  # the training views' detectors
        return position_std_A(atoms.sigmas, atoms.amplitudes, axes, series.pixel_size_A, noise, self.config.loss), noise

    def write_results(self, run_dir: Path) -> dict | None:
        """Write ``atoms.xyz``, ``atoms.csv`` (with each atom's position precision), ``slices.png``
        (central slices of the potential, with the true atoms when known) and, with a truth
        file, ``evaluation.json``."""
        self.finalize()
        atoms = self.atoms()
        precision = self.position_std_A(atoms)
        if precision is not None:
            atoms.position_std_A, noise = precision
            CONSOLE.print(
                f"gaussian-atoms: residual noise {noise:.4g} (input units); median position precision "
                + ", ".join(f"{a} {v * 100:.1f} pm" for a, v in zip("xyz", np.median(atoms.position_std_A, axis=0)))
            )
        write_atoms(atoms, run_dir / "atoms.xyz")
        write_atoms(atoms, run_dir / "atoms.csv")
        CONSOLE.print(f"[bold]gaussian-atoms[/bold]: wrote {len(atoms)} atoms to {run_dir / 'atoms.xyz'}")
        truth = read_atoms(self.truth_path) if self.truth_path is not None else None
        scores = score_atoms(atoms.positions, truth.positions) if truth is not None else None
        if len(atoms):
            title = f"{len(atoms)} atoms" + (
                f"; against the truth: TPR {scores['tpr']:.4f}, FP/atom {scores['fp_per_true_atom']:.4f}, RMSD {scores['rmsd_pm']:.1f} pm" if scores else ""
            )
            write_slices_png(atoms, run_dir / "slices.png", truth, title=title)
        if scores is None:
            return None
        (run_dir / "evaluation.json").write_text(json.dumps(scores, indent=2) + "\n")
        CONSOLE.print(f"[bold]gaussian-atoms[/bold]: against {self.truth_path}: {json.dumps(scores)}")
        return scores
