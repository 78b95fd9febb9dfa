"""Density control on plain parameter dicts and Adam optimisers, without nerfstudio.

Positions and widths are in normalised units with ``length_scale`` 0.1 per Å (a 100 Å box
is the volume [-0.5, 0.5]); float64 so that conserved masses compare to 1e-12."""

import math

import pytest
import torch

from gaussian_atoms_method.density.strategy import DensityControl, amplitudes, widths
from gaussian_atoms_method.physics.projector import gaussian_mass


def _setup(positions_A, sigma_A=0.6, amplitude=1.0, **settings):
    n = len(positions_A)
    params = torch.nn.ParameterDict(
        {
            "means": torch.nn.Parameter(torch.tensor(positions_A, dtype=torch.float64)),
            "log_sigmas": torch.nn.Parameter(torch.full((n, 1), math.log(sigma_A), dtype=torch.float64)),
            "log_amplitudes": torch.nn.Parameter(torch.full((n, 1), math.log(amplitude), dtype=torch.float64)),
        }
    )
    # One step at a zero learning rate: Adam then holds per-Gaussian moments that must follow
    # the remaps, and the parameters are as given.
    optimizers = {k: torch.optim.Adam([p], lr=0.0) for k, p in params.items()}
    sum((p**2).sum() for p in params.values()).backward()
    for p, opt in zip(params.values(), optimizers.values()):
        opt.step()
        p.grad = None
    settings.setdefault("max_log_amplitude", 50.0)
    control = DensityControl(length_scale=1.0, generator=torch.Generator().manual_seed(0), **settings)
    control.reset(n)
    return params, optimizers, control


def _mass(params, control):
    return gaussian_mass(widths(params, control.min_log_sigma), amplitudes(params))


def test_two_atoms_a_carbon_bond_apart_are_both_kept():
    """1.42 Å (C-C) is twice the 0.7 Å merge threshold: no merge, no prune."""
    params, opts, control = _setup([[0.0, 0.0, 0.0], [0.142, 0.0, 0.0]], sigma_A=0.06)
    control.length_scale = 0.1  # 0.1 normalised units per Å: the pair is 1.42 Å apart
    assert control.merge(params, opts) == 0
    assert control.prune(params, opts) == 0
    assert params["means"].shape[0] == 2


def test_close_pair_merges_with_mass_conserved_and_moments_remapped():
    params, opts, control = _setup([[0.0, 0.0, 0.0], [0.03, 0.0, 0.0], [0.3, 0.0, 0.0]], sigma_A=0.06)
    control.length_scale = 0.1  # 0.3 Å apart: one atom; the third 3 Å away
    before = _mass(params, control).detach()
    assert control.merge(params, opts) == 1
    after = _mass(params, control).detach()
    assert after[0] == pytest.approx(float(before[:2].sum()), rel=1e-12)
    assert float(params["means"][0, 0].detach()) == pytest.approx(0.015, abs=1e-12)
    assert opts["means"].state[params["means"]]["exp_avg"].shape == (2, 3)


def test_noise_blob_is_pruned_and_atoms_stay():
    params, opts, control = _setup([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [-0.3, 0.0, 0.0], [0.0, 0.3, 0.0]], sigma_A=0.06)
    control.length_scale = 0.1
    with torch.no_grad():
        params["log_amplitudes"][3] -= math.log(100.0)  # 1% of an atom's mass: far below the 0.25 fraction
    assert control.prune(params, opts) == 1
    assert params["means"].shape[0] == 3 and float(params["means"][:, 1].abs().max()) == 0.0


def test_too_wide_and_outside_are_pruned():
    params, opts, control = _setup([[0.0, 0.0, 0.0], [0.2, 0.0, 0.0], [0.0, 0.45, 0.0], [0.6, 0.0, 0.0]], sigma_A=0.06)
    control.length_scale = 0.1  # max_atom_sigma_A 1.5 Å = 0.15 normalised
    with torch.no_grad():
        params["log_sigmas"][1] = math.log(0.2)  # 2 Å wide: no atom
    assert control.prune(params, opts) == 2  # the wide one, and the one outside [-0.5, 0.5]
    assert params["means"].shape[0] == 2


def test_pulled_gaussian_is_duplicated_with_half_the_mass_each():
    params, opts, control = _setup([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0]], sigma_A=0.06, densify_grad_thresh=0.2)
    control.length_scale = 0.1
    control.grad_accum = torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]]) * 3
    control.grad_count = 3
    before = _mass(params, control).detach()
    assert control.densify(params, opts) == 1
    after = _mass(params, control).detach()
    assert params["means"].shape[0] == 3
    assert float(after[1] + after[2]) == pytest.approx(float(before[1]), rel=1e-12)
    gap = float((params["means"][1] - params["means"][2]).norm())
    assert gap == pytest.approx(0.06, rel=1e-6)  # one width apart (the direction is drawn in float32)
    assert opts["log_amplitudes"].state[params["log_amplitudes"]]["exp_avg"].shape == (3, 1)


def test_refine_runs_only_on_refine_steps_after_the_warm_up():
    params, opts, control = _setup([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0]], sigma_A=0.06, warmup_length=200, refine_every=100)
    control.length_scale = 0.1
    with torch.no_grad():
        params["log_amplitudes"][1] -= math.log(100.0)
    assert control.step_post_backward(params, opts, 100) == {}  # warm-up
    assert control.step_post_backward(params, opts, 250) == {}  # not a refine step
    assert control.step_post_backward(params, opts, 300)["pruned"] == 1


def test_clamp_keeps_runaway_values_finite():
    params, opts, control = _setup([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0]], sigma_A=0.06, min_sigma_A=0.15, max_sigma_A=5.0, max_log_amplitude=3.0)
    control.length_scale = 0.1
    with torch.no_grad():
        params["log_sigmas"][0] = 50.0
        params["log_sigmas"][1] = -50.0
        params["log_amplitudes"][0] = 1e4
        params["means"][1] = 1e6
    control.clamp(params)
    assert torch.exp(params["log_sigmas"]).flatten().tolist() == pytest.approx([0.5, 0.015])
    assert float(params["log_amplitudes"].max()) == 3.0 and float(params["means"].abs().max()) == 1.0


def test_safeguards_are_counted_and_reported():
    """Clamps and out-of-volume prunes are counted over the run and reported in words; an
    atom-like Gaussian outside the volume is named as such (atoms may be lost)."""
    params, opts, control = _setup([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [0.0, 0.7, 0.0]], sigma_A=0.06)
    control.length_scale = 0.1
    assert control.report() == []
    with torch.no_grad():
        params["log_sigmas"][0] = -50.0
    control.clamp(params)
    control.clamp(params)  # already in range: not counted again
    with torch.no_grad():
        params["log_sigmas"][0] = math.log(0.06)  # an atom again, so only the outside one is pruned
    assert control.prune(params, opts) == 1
    lines = control.report()
    assert lines[0] == "clamped (Gaussian-steps): 1 widths held at the 0.15 Å floor"
    assert lines[1].startswith("1 Gaussians left the reconstruction volume") and "1 of them atom-like" in lines[1]
