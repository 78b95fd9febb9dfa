"""The ``gaussian-atoms`` method as nerfstudio sees it: trainer, pipeline and optimiser settings.

Learning rates are in normalised units (the detector's longer side is 1); the means' rate
decays tenfold over the run so that atoms settle to pm precision.
"""

from __future__ import annotations

from nerfstudio.configs.base_config import ViewerConfig
from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanager, FullImageDatamanagerConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig
from nerfstudio.plugins.types import MethodSpecification

from dataparsers.tilt_series_dataparser import TiltSeriesDataParserConfig
from dataparsers.tilt_series_dataset import TiltSeriesDataset

from gaussian_atoms_method.nerfstudio_layer.model import GaussianAtomsModelConfig
from gaussian_atoms_method.nerfstudio_layer.trainer import GaussianAtomsTrainerConfig

MAX_ITERATIONS = 3000


class TiltSeriesDatamanager(FullImageDatamanager[TiltSeriesDataset]):
    """nerfstudio's full-image datamanager serving float projections from memory."""


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
                "optimizer": AdamOptimizerConfig(lr=1e-3, eps=1e-15),
                "scheduler": ExponentialDecaySchedulerConfig(lr_final=1e-4, max_steps=max_iterations),
            },
            "log_sigmas": {"optimizer": AdamOptimizerConfig(lr=5e-3, eps=1e-15), "scheduler": None},
            "log_amplitudes": {"optimizer": AdamOptimizerConfig(lr=2e-2, eps=1e-15), "scheduler": None},
            # Only with --pipeline.model.isotropic False (the ablation).
            "quats": {"optimizer": AdamOptimizerConfig(lr=1e-3, eps=1e-15), "scheduler": None},
            # Only with --pipeline.model.background constant|plane (projection units, normalised).
            "background": {"optimizer": AdamOptimizerConfig(lr=1e-1, eps=1e-15), "scheduler": None},
            # The point-spread function's weights (--pipeline.model.psf learned, physics/psf.py):
            # shared by every view, so they move every step; Adam's step is about the rate, so
            # 2e-3 takes a weight from 0 to a fifth of the intensity in about 100 steps and
            # leaves it within 0.2% once fitted.
            "psf": {"optimizer": AdamOptimizerConfig(lr=2e-3, eps=1e-15), "scheduler": None},
            # Only with --pipeline.model.refine-alignment True (normalised lengths).  Each view's
            # shift moves only on the steps that render it (1 in 47 on the Au series, ~64 in
            # 3,000 steps): 2e-3 per update (0.14 Å on a 70 Å detector) lets a 1 Å error close
            # within the first third of the run; 1e-4 at the end keeps it steady.
            "view_shifts": {
                "optimizer": AdamOptimizerConfig(lr=2e-3, eps=1e-15),
                "scheduler": ExponentialDecaySchedulerConfig(lr_final=1e-4, max_steps=max_iterations),
            },
            # Only with --pipeline.model.refine-tilts True (radians; 5e-4 per update ~ 0.03 deg).
            "view_tilts": {
                "optimizer": AdamOptimizerConfig(lr=5e-4, eps=1e-15),
                "scheduler": ExponentialDecaySchedulerConfig(lr_final=2e-5, max_steps=max_iterations),
            },
        },
        viewer=ViewerConfig(num_rays_per_chunk=1 << 15),
        vis="viewer",
    )


gaussian_atoms_method = MethodSpecification(
    config=gaussian_atoms_trainer_config(),
    description="Atomic electron tomography: one isotropic 3D Gaussian per atom, fitted to a tilt series.",
)
