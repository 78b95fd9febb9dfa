"""The ``gaussian-atoms`` method as nerfstudio sees it: trainer, pipeline and optimiser settings.

Learning rates are in normalised units (the detector's longer side is 1); the means' rate
decays tenfold over the run so that atoms settle to pm precision.
"""

from __future__ import annotations

import inspect
import sys
from dataclasses import dataclass
from pathlib import Path

import torch
from nerfstudio.configs.base_config import MachineConfig, ViewerConfig
from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanager, FullImageDatamanagerConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig
from nerfstudio.plugins.types import MethodSpecification

from dataparsers.tilt_series_dataparser import TiltSeriesDataParserConfig
from dataparsers.tilt_series_dataset import TiltSeriesDataset
from gaussian_atoms_method.nerfstudio_layer.model import GaussianAtomsModelConfig
from gaussian_atoms_method.nerfstudio_layer.trainer import GaussianAtomsTrainerConfig
from gaussian_atoms_method.physics.devices import default_device
from gaussian_atoms_method.start_ahead import begin_for

MAX_ITERATIONS = 3000

if Path(sys.argv[0]).name == "ns-train" and sys.argv[1:2] == ["gaussian-atoms"]:
    # ns-train imports this module while it loads every method it knows, before it parses the
    # command line: the start of the run it was asked for begins now, in a thread (start_ahead).
    begin_for(sys.argv[2:])


class Adam(torch.optim.Adam):
    """PyTorch's Adam, whose step does not import torch's compiler front end (dynamo) while
    nothing else has: the stock step imports it at its first call to mark graph breaks for
    compiled code (0.7 s on the H100 machine, 2.8 s on the 2-core CPU, on the way to the first
    training step); in eager mode those marks do nothing, and the step is the update itself
    with gradients off, as the stock one runs it (test_deferred_imports)."""

    def step(self, closure=None):
        if "torch._dynamo" in sys.modules and _WITH_GRAPH_BREAKS is not None:  # something compiles, or may
            return _WITH_GRAPH_BREAKS(self, closure)
        with torch.set_grad_enabled(self.defaults["differentiable"]):
            return _UPDATE(self, closure)


def _wrapper_layer(fn, name: str):
    """The layer of the decorated ``fn`` whose code is named ``name`` (None if none is)."""
    while fn is not None and getattr(getattr(fn, "__code__", None), "co_name", None) != name:
        fn = getattr(fn, "__wrapped__", None)
    return fn


_UPDATE = inspect.unwrap(torch.optim.Adam.step)  # the update, without the stock step's wrappers
# the stock step without its profiling hooks (this class's own step has them)
_WITH_GRAPH_BREAKS = _wrapper_layer(torch.optim.Adam.step, "_use_grad")


@dataclass
class AdamConfig(AdamOptimizerConfig):
    """nerfstudio's Adam (:class:`Adam`), fused into one kernel a step where its parameters lie
    on a GPU (PyTorch's ``fused``; its default there launches about ten per parameter group a
    step, and the five groups' steps took 1.8 ms of an 8 ms step at 20,000 atoms on the H100)."""

    def setup(self, params) -> torch.optim.Optimizer:
        params = list(params)
        fused = bool(params) and all(p.is_cuda for p in params)
        return Adam(params, lr=self.lr, eps=self.eps, weight_decay=self.weight_decay, fused=fused or None)


class TiltSeriesDatamanager(FullImageDatamanager[TiltSeriesDataset]):
    """nerfstudio's full-image datamanager serving float projections from memory.  Each view's
    camera is cut from the set once and kept: nerfstudio cuts and copies it at every step,
    1.2 of the 10 ms a training step took at 20,000 atoms on the H100 (cProfile).  So is its
    image on the device: a plain copy to the GPU at every step waited for the queued steps
    (``torch.cuda.set_sync_debug_mode``)."""

    def next_train(self, step: int):
        """The next training view's camera (``metadata["cam_idx"]``: its index) and its data, in
        nerfstudio's order (:meth:`FullImageDatamanager.next_train`)."""
        image_idx = self.train_unseen_cameras.pop(0)
        if len(self.train_unseen_cameras) == 0:
            self.train_unseen_cameras = self.sample_train_cameras()
        # a copy: the cache is not changed (reading it first loads it, and the cameras)
        data = dict(self.cached_train[image_idx])
        cameras, images = self.__dict__.setdefault("_view_cameras", {}), self.__dict__.setdefault("_view_images", {})
        if image_idx not in cameras:
            camera = self.train_cameras[image_idx : image_idx + 1].to(self.device)
            camera.metadata = {**(camera.metadata or {}), "cam_idx": image_idx}
            cameras[image_idx] = camera
            images[image_idx] = data["image"].to(self.device)
        data["image"] = images[image_idx]
        return cameras[image_idx], data


def gaussian_atoms_trainer_config(max_iterations: int = MAX_ITERATIONS) -> GaussianAtomsTrainerConfig:
    """The default configuration of ``ns-train gaussian-atoms``."""
    return GaussianAtomsTrainerConfig(
        method_name="gaussian-atoms",
        steps_per_eval_image=500,
        steps_per_eval_batch=0,
        steps_per_save=1000,
        steps_per_eval_all_images=100000,
        max_num_iterations=max_iterations,
        mixed_precision=False,
        machine=MachineConfig(device_type=default_device()),
        pipeline=VanillaPipelineConfig(
            datamanager=FullImageDatamanagerConfig(
                _target=TiltSeriesDatamanager,
                dataparser=TiltSeriesDataParserConfig(),
                # "gpu" means "on the training device"; "cpu" pins memory, which needs CUDA.
                cache_images="gpu",
                cache_images_type="float32",
            ),
            model=GaussianAtomsModelConfig(),
        ),
        optimizers={
            "means": {
                "optimizer": AdamConfig(lr=1e-3, eps=1e-15),
                "scheduler": ExponentialDecaySchedulerConfig(lr_final=1e-4, max_steps=max_iterations),
            },
            "log_sigmas": {"optimizer": AdamConfig(lr=5e-3, eps=1e-15), "scheduler": None},
            "log_amplitudes": {"optimizer": AdamConfig(lr=2e-2, eps=1e-15), "scheduler": None},
            # Only with --pipeline.model.isotropic False (the ablation).
            "quats": {"optimizer": AdamConfig(lr=1e-3, eps=1e-15), "scheduler": None},
            # With a background: solved in closed form (floors.py), not by this optimiser, whose
            # group stays so that checkpoints with its state load.
            "background": {"optimizer": AdamConfig(lr=1e-1, eps=1e-15), "scheduler": None},
            # The point-spread function's weights (--pipeline.model.psf learned, physics/psf.py):
            # shared by every view, so they move every step; Adam's step is about the rate, so
            # 2e-3 takes a weight from 0 to a fifth of the intensity in about 100 steps and
            # leaves it within 0.2% once fitted.
            "psf": {"optimizer": AdamConfig(lr=2e-3, eps=1e-15), "scheduler": None},
            # Only with --pipeline.model.refine-alignment True (normalised lengths).  Each view's
            # shift moves only on the steps that render it (1 in 47 on the Au series, ~64 in
            # 3,000 steps): 2e-3 per update (0.14 Å on a 70 Å detector) lets a 1 Å error close
            # within the first third of the run; 1e-4 at the end keeps it steady.
            "view_shifts": {
                "optimizer": AdamConfig(lr=2e-3, eps=1e-15),
                "scheduler": ExponentialDecaySchedulerConfig(lr_final=1e-4, max_steps=max_iterations),
            },
            # Only with --pipeline.model.refine-tilts True (radians; 5e-4 per update ~ 0.03 deg).
            "view_tilts": {
                "optimizer": AdamConfig(lr=5e-4, eps=1e-15),
                "scheduler": ExponentialDecaySchedulerConfig(lr_final=2e-5, max_steps=max_iterations),
            },
        },
        # this machine only, unless --viewer.websocket-host says more
        viewer=ViewerConfig(num_rays_per_chunk=1 << 15, websocket_host="127.0.0.1"),
        vis="viewer",
    )


gaussian_atoms_method = MethodSpecification(
    config=gaussian_atoms_trainer_config(),
    description="Atomic electron tomography: one isotropic 3D Gaussian per atom, fitted to a tilt series.",
)
