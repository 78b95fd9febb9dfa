"""Iterate averaging (gaussian_atoms_method.density.averaging): the window's mean, its
windows, and the jitter it removes."""

from __future__ import annotations

import math

import torch

from gaussian_atoms_method.density.averaging import AVERAGED, IterateAverage
from gaussian_atoms_method.density.strategy import DensityControl


def _params(n: int, generator: torch.Generator) -> torch.nn.ParameterDict:
    return torch.nn.ParameterDict(
        {
            "means": torch.nn.Parameter(torch.rand(n, 3, generator=generator) - 0.5),
            "log_sigmas": torch.nn.Parameter(torch.full((n, 1), -3.0)),
            "log_amplitudes": torch.nn.Parameter(torch.zeros(n, 1)),
        }
    )


def test_the_window_mean_is_the_mean_of_the_iterates():
    """Against the float64 mean of the same iterates: the float32 sums of deviations from the
    first iterate lose only float32 rounding (1e-7 of the coordinates' unit size)."""
    g = torch.Generator().manual_seed(0)
    params, average, seen = _params(50, g), IterateAverage(), []
    for _ in range(37):
        params["means"].data += 0.01 * torch.randn(50, 3, generator=g)
        params["log_amplitudes"].data += 0.1 * torch.randn(50, 1, generator=g)
        average.add(params)
        seen.append({n: p.detach().double().clone() for n, p in params.items()})
    mean = average.mean(params)
    for name in params:  # the positions averaged; the masses and widths as they stand (AVERAGED)
        expected = torch.stack([s[name] for s in seen]).mean(dim=0) if name in AVERAGED else seen[-1][name]
        assert torch.allclose(mean[name].double(), expected, atol=1e-6)
    assert average.close(params) == 37
    assert torch.allclose(params["means"].double(), torch.stack([s["means"] for s in seen]).mean(dim=0), atol=1e-6)
    assert average.count == 0


def test_a_changed_set_of_gaussians_opens_a_new_window():
    """A duplicate, prune or merge replaces the parameter tensors: the iterates before it are of
    other Gaussians and are dropped; closing on tensors the window does not hold writes nothing."""
    g = torch.Generator().manual_seed(1)
    params, average = _params(10, g), IterateAverage()
    for _ in range(5):
        average.add(params)
    params["means"] = torch.nn.Parameter(params["means"].data[:8].clone())
    before = params["means"].detach().clone()
    assert average.close(params) == 0
    assert torch.equal(params["means"], before)
    for _ in range(3):
        average.add(params)
    assert average.count == 3


def test_averaging_removes_jitter_as_the_square_root_of_the_window():
    """Iterates that scatter independently about the fit by sigma: the mean of n lies sigma /
    sqrt(n) from it.  With 3 x 2,000 coordinates the RMS error's relative standard deviation is
    1 / sqrt(2 x 6,000) = 0.9%, so 10% is over ten of them."""
    g = torch.Generator().manual_seed(2)
    params, average, sigma, n = _params(2000, g), IterateAverage(), 0.02, 100
    fit = params["means"].detach().clone()
    for _ in range(n):
        params["means"].data = fit + sigma * torch.randn(fit.shape, generator=g)
        average.add(params)
    last_rms = float((params["means"].detach() - fit).square().mean().sqrt())
    average.close(params)
    rms = float((params["means"].detach() - fit).square().mean().sqrt())
    assert abs(last_rms / sigma - 1.0) < 0.1
    assert abs(rms / (sigma / math.sqrt(n)) - 1.0) < 0.1


def test_the_density_control_closes_the_window_at_each_refine():
    """step_post_backward adds every step and, at a refine step, writes the interval's mean into
    the parameters before it duplicates or prunes; without average_iterates the last iterate stays."""
    for averaging in (True, False):
        g = torch.Generator().manual_seed(3)
        params = _params(20, g)
        control = DensityControl(
            length_scale=1.0,
            max_log_amplitude=10.0,
            generator=g,
            refine_every=10,
            warmup_length=1000,
            average_iterates=averaging,
        )
        trajectory = []
        for step in range(1, 11):
            params["means"].data += 0.001 * torch.randn(20, 3, generator=g)
            trajectory.append(params["means"].detach().clone())
            control.step_post_backward(params, {}, step)
        expected = torch.stack(trajectory).mean(dim=0) if averaging else trajectory[-1]
        assert torch.allclose(params["means"].detach(), expected, atol=1e-6)
