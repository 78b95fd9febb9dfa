"""The model's options as nerfstudio sees them (``--pipeline.model.*``): splatfacto's config with
the fit's options (:class:`~gaussian_atoms_method.engine.options.FitOptions`) in place of its
own, and splatfacto's that do nothing here hidden.  :class:`~.model.GaussianAtomsModelConfig`
adds only the model class it builds.
"""

from __future__ import annotations

import dataclasses
import inspect
from dataclasses import dataclass
from typing import Annotated, get_type_hints

import tyro
from nerfstudio.models.splatfacto import SplatfactoModelConfig

from gaussian_atoms_method.engine.options import FitOptions, field_docs

INERT_SPLATFACTO = (
    "background_color",
    "camera_optimizer",
    "collider_params",
    "color_corrected_metrics",
    "cull_alpha_thresh",
    "cull_scale_thresh",
    "cull_screen_size",
    "densify_size_thresh",
    "enable_collider",
    "eval_num_rays_per_chunk",
    "grid_shape",
    "loss_coefficients",
    "max_gauss_ratio",
    "n_split_samples",
    "num_downscales",
    "output_depth_during_training",
    "prompt",
    "random_init",
    "random_scale",
    "rasterize_mode",
    "reset_alpha_every",
    "resolution_schedule",
    "sh_degree",
    "sh_degree_interval",
    "split_screen_size",
    "ssim_lambda",
    "stop_screen_size_at",
    "use_absgrad",
    "use_bilateral_grid",
    "use_scale_regularization",
)
"""splatfacto's options that do nothing here (colours, alpha compositing, screen-space culling, SSIM,
cameras' optimisation): kept on the config, so nerfstudio's code and old config.yml files read them,
and left out of ``--help`` and the command line."""


def inert_splatfacto_fields() -> dict:
    """For each of :data:`INERT_SPLATFACTO`: its type marked for tyro to suppress, and its field
    with splatfacto's default."""
    hints = get_type_hints(SplatfactoModelConfig, include_extras=True)
    base = {f.name: f for f in dataclasses.fields(SplatfactoModelConfig)}
    out = {}
    for name in INERT_SPLATFACTO:
        out[name] = (Annotated[hints[name], tyro.conf.Suppress], _copy(base[name]))
    return out


def fit_fields_over_splatfacto() -> dict:
    """For each option splatfacto's config also has (``refine_every``, ``warmup_length``, ...):
    the fit's type, help and field, so that the fit's value and text, not splatfacto's, are
    the default and the ``--help``."""
    hints, docs = get_type_hints(FitOptions, include_extras=True), field_docs(FitOptions)
    splatfacto = {f.name for f in dataclasses.fields(SplatfactoModelConfig)}
    return {
        f.name: (
            Annotated[hints[f.name], tyro.conf.arg(help=inspect.cleandoc(docs[f.name]) if f.name in docs else None)],
            _copy(f),
        )
        for f in dataclasses.fields(FitOptions)
        if f.name in splatfacto
    }


def _copy(f: dataclasses.Field):
    if f.default is not dataclasses.MISSING:
        return dataclasses.field(default=f.default)
    return dataclasses.field(default_factory=f.default_factory)


@dataclass
class GaussianAtomsOptions(SplatfactoModelConfig, FitOptions):
    """Gaussian atoms: isotropic 3D Gaussians fitted to a tilt series.

    The fit's options come first (:class:`FitOptions`, the last base); splatfacto's own follow,
    hidden."""

    __annotations__ = {}  # filled below (a class body without annotations has none)
    for _name, (_type, _field) in (inert_splatfacto_fields() | fit_fields_over_splatfacto()).items():
        __annotations__[_name] = _type  # redeclared: the fit's default, or hidden from the command line
        vars()[_name] = _field
    del _name, _type, _field
