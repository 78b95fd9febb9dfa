"""The run's actions at the convergence checks (:mod:`.stopping`): the positions' rate in
detector pixels and its halving, on a real nerfstudio optimiser and schedule."""

import math
from types import SimpleNamespace

import pytest
import torch
from nerfstudio.engine.optimizers import Optimizers

from gaussian_atoms_method.engine.stopping import set_position_rate, slow_positions
from gaussian_atoms_method.engine.view_set import ViewSet
from gaussian_atoms_method.nerfstudio_layer.config import gaussian_atoms_trainer_config


def _model_and_optimizers(pixel_A=0.25, detector_px=271, rate_px=1 / math.sqrt(12)):
    params = {"means": [torch.nn.Parameter(torch.zeros(3, 3))]}
    config = gaussian_atoms_trainer_config(max_iterations=3000)
    optimizers = Optimizers({"means": config.optimizers["means"]}, params)
    model = SimpleNamespace(
        config=SimpleNamespace(position_rate_px=rate_px),
        view_set=ViewSet(pixel_size_A=pixel_A),
        normalisation=SimpleNamespace(length_scale=1.0 / (detector_px * pixel_A)),
        _optimizers_obj=optimizers,
    )
    return model, optimizers


def _lr(optimizers):
    return optimizers.optimizers["means"].param_groups[0]["lr"]


@pytest.mark.parametrize("detector_px", [271, 497])
def test_the_position_rate_is_in_pixels_whatever_the_field(detector_px):
    """0.2887 pixels of 0.25 Å is 0.0722 Å a step on any detector, normalised by its own
    width; the schedule's tenfold decay is kept; a second call (a resumed optimiser) does nothing."""
    model, optimizers = _model_and_optimizers(detector_px=detector_px)
    ls = model.normalisation.length_scale
    assert set_position_rate(model, optimizers) and not set_position_rate(model, optimizers)
    assert _lr(optimizers) / ls == pytest.approx(0.25 / math.sqrt(12))
    for _ in range(3000):
        optimizers.scheduler_step_all(0)
    assert _lr(optimizers) / ls == pytest.approx(0.025 / math.sqrt(12), rel=1e-3)


def test_none_keeps_the_configured_rate():
    model, optimizers = _model_and_optimizers(rate_px=None)
    assert not set_position_rate(model, optimizers) and _lr(optimizers) == pytest.approx(1e-3)


def test_slowing_halves_the_rate_and_its_schedule_down_to_the_final_rate():
    """Halving scales the optimiser's rate and the schedule's base (the next scheduler step
    keeps it); it stops before the rate would fall below the schedule's final one (a tenth)."""
    model, optimizers = _model_and_optimizers()
    set_position_rate(model, optimizers)
    start = _lr(optimizers)
    assert slow_positions(model) and _lr(optimizers) == pytest.approx(start / 2)
    optimizers.scheduler_step_all(0)
    assert _lr(optimizers) == pytest.approx(start / 2, rel=1e-3)
    halvings = 1 + sum(slow_positions(model) for _ in range(10))
    assert halvings == 3 and start / 10 <= _lr(optimizers) == pytest.approx(start / 8, rel=1e-3)
