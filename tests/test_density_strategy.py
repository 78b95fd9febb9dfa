"""Density control on plain parameter dicts and Adam optimisers, without nerfstudio.

Positions and widths are in normalised units with ``length_scale`` 0.1 per Å (a 100 Å box
is the volume [-0.5, 0.5]); float64 so that conserved masses compare to 1e-12."""

import math

import numpy as np
import pytest
import torch

from gaussian_atoms_method.density.parameters import amplitudes, split_width, split_worth, widths
from gaussian_atoms_method.density.remap import duplicate_remap
from gaussian_atoms_method.density.strategy import DensityControl
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
    control.state.grad_accum = torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]]) * 3
    control.state.grad_count = 3
    before = _mass(params, control).detach()
    assert control.densify(params, opts) == 1
    after = _mass(params, control).detach()
    assert params["means"].shape[0] == 3
    assert float(after[1] + after[2]) == pytest.approx(float(before[1]), rel=1e-12)
    gap = float((params["means"][1] - params["means"][2]).norm())
    assert gap == pytest.approx(0.06, rel=1e-6)  # one width apart (the direction is drawn in float32)
    assert opts["log_amplitudes"].state[params["log_amplitudes"]]["exp_avg"].shape == (3, 1)


def test_refine_runs_only_on_refine_steps_after_the_warm_up():
    params, opts, control = _setup(
        [[0.0, 0.0, 0.0], [0.3, 0.0, 0.0]], sigma_A=0.06, warmup_length=200, refine_every=100
    )
    control.length_scale = 0.1
    with torch.no_grad():
        params["log_amplitudes"][1] -= math.log(100.0)
    assert control.step_post_backward(params, opts, 100) == {}  # warm-up
    assert control.step_post_backward(params, opts, 250) == {}  # not a refine step
    assert control.step_post_backward(params, opts, 300)["pruned"] == 1


def test_clamp_keeps_runaway_values_finite():
    params, opts, control = _setup(
        [[0.0, 0.0, 0.0], [0.3, 0.0, 0.0]], sigma_A=0.06, min_sigma_A=0.15, max_sigma_A=5.0, max_log_amplitude=3.0
    )
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
    # the volume is the field: the object may be a film the run did not read as one
    assert "extended_object on" in lines[1]
    control.field_half_extent = (0.5, 0.5, 0.5)  # a film's volume, wider than its field: nothing to suggest
    assert "extended_object" not in control.report()[1]


def _with_noise(control, read_var=1.0, gain=0.0, pixel_size=0.025, n_views=50, view_dirs=None):
    from gaussian_atoms_method.physics.noise import NoiseModel

    control.noise, control.pixel_size, control.n_views = NoiseModel(read_var, gain), pixel_size, n_views
    control.view_dirs = view_dirs
    return control


def test_a_gaussian_that_left_the_volume_is_named_atom_like_by_the_noise_the_run_ends_in():
    """Whether a Gaussian that left the volume was an atom is judged at the run's end, at the
    confident atoms' level under the noise the final prune judges in: two that left proven at
    three times that level under the noise read before training are noise once the residual over
    an atom reads ten times its standard deviation (aSi-208 at 8e3 had named 243 on correct
    geometry)."""
    params, opts, control = _setup([[0.0, 0.0, 0.0], [0.0, 0.7, 0.0], [0.7, 0.0, 0.0]], sigma_A=0.06)
    control.length_scale = 0.1
    _with_noise(control)
    z_unit = float(control.mass_significance(params)[0])
    with torch.no_grad():
        params["log_amplitudes"][:] = math.log(3.0 * control.significance_threshold() / z_unit)
    assert control.prune(params, opts) == 2
    assert "2 of them atom-like" in control.report()[0]
    control.noise = type(control.noise)(100.0, 0.0)  # the residual over an atom, judged after the fit
    assert control.report() == ["2 Gaussians left the reconstruction volume and were pruned"]


def _tilt_series_dirs(step_deg=3.0, max_deg=70.0):
    """Beam directions of a single-axis series about y, -70:3:70 degrees (the limited range)."""
    t = torch.deg2rad(torch.arange(-max_deg, max_deg + 1e-9, step_deg, dtype=torch.float64))
    return torch.stack([torch.sin(t), torch.zeros_like(t), torch.cos(t)], dim=1)


def _pair_along_the_wedge(separation_A, sigma_A, each_significance):
    """Two Gaussians ``separation_A`` apart along z (the direction the missing wedge blurs) in a
    100 Å box at 0.25 Å pixels, unit additive noise, L1 efficiency, each of the given mass
    significance; returns params, optimisers, control."""
    params, opts, control = _setup(
        [[0.0, 0.0, 0.0], [0.0, 0.0, separation_A * 0.01]], sigma_A=sigma_A * 0.01, min_sigma_A=0.01
    )
    control.length_scale = 0.01
    dirs = _tilt_series_dirs()
    _with_noise(control, pixel_size=0.0025, n_views=len(dirs), view_dirs=dirs)
    control.efficiency = math.pi / 2
    z_unit = float(control.mass_significance(params)[0])  # amplitude 1
    with torch.no_grad():
        params["log_amplitudes"][:] = math.log(each_significance / z_unit)
    return params, opts, control


def test_an_atom_shared_along_the_missing_wedge_is_merged_and_judged_whole():
    """At Au noise 500 (docs/results.md) a whole atom's mass stands about 7.3 of its standard
    deviations high, above the final prune's 5.33 for a 100 Å box; the fit can share it between
    two Gaussians 1.2 Å apart along the wedge, 3.65 each, which the prune alone would both drop.
    Merging the pair changes the projections by a chi-square of about 6 against the level of
    42 (5 degrees of freedom, same family-wise rate): the data cannot resolve it, so finalize
    makes one Gaussian with the whole mass at the centre of mass, and keeps it."""
    params, opts, control = _pair_along_the_wedge(1.2, 0.45, 3.65)
    total = float(_mass(params, control).sum())
    assert len(control.unresolved_pairs(params, torch.ones(2, dtype=torch.bool))) == 1
    finalize_params, finalize_opts, finalize_control = _pair_along_the_wedge(1.2, 0.45, 3.65)
    assert finalize_control.finalize(finalize_params, finalize_opts) == 1
    assert finalize_params["means"].shape[0] == 1
    assert float(_mass(finalize_params, finalize_control)[0]) == pytest.approx(total, rel=1e-9)
    assert float(finalize_params["means"][0, 2]) == pytest.approx(0.006, rel=1e-9)
    assert control.prune(params, opts, final=True) == 2  # judged apart, the atom was lost


def test_carbon_neighbours_along_the_wedge_stay_two():
    """Two C atoms 1.42 Å apart along the wedge, each 15 sigma (well above the prune's level):
    merging them would cost a chi-square near 275, far above 42; both stay."""
    params, opts, control = _pair_along_the_wedge(1.42, 0.35, 15.0)
    assert control.finalize(params, opts) == 0
    assert params["means"].shape[0] == 2


def test_mass_significance_matches_the_numerical_fisher_information():
    """Var(mass) = 8 pi s^2 v / V for a 2D Gaussian fitted with its width: checked against the
    Fisher information of (mass, width) summed over a pixel grid (float64, central
    differences), for widths of 1.5-4 pixels (atoms at 0.2-0.4 Å pixels): within 2%."""
    import numpy as np

    for s_px in (1.5, 2.4, 4.0):
        y, x = np.mgrid[-30:31, -30:31].astype(np.float64)

        def image(mass, s):
            return mass * np.exp(-(x**2 + y**2) / (2 * s**2)) / (2 * np.pi * s**2)

        h = 1e-5
        d_mass = (image(1 + h, s_px) - image(1 - h, s_px)) / (2 * h)
        d_width = (image(1, s_px + h) - image(1, s_px - h)) / (2 * h)
        jac = np.stack([d_mass.ravel(), d_width.ravel()])
        views, var = 50, 2.0
        fisher = views * jac @ jac.T / var
        sd_numeric = np.sqrt(np.linalg.inv(fisher)[0, 0])
        params, _, control = _setup([[0.0, 0.0, 0.0]], sigma_A=s_px * 0.025, amplitude=1.0, min_sigma_A=0.01)
        _with_noise(control, read_var=var, pixel_size=0.025, n_views=views)
        mass = float(_mass(params, control)[0])  # normalised units: pixel area 0.025^2
        z = float(control.mass_significance(params)[0])
        sd_formula = mass / z / 0.025**2  # back to pixel units
        assert sd_formula == pytest.approx(sd_numeric, rel=0.02)


def test_final_prune_by_significance_keeps_a_faint_atom_and_drops_a_noise_blob():
    """With the noise known, the final prune asks whether each mass is significantly above zero:
    a light atom at 9 sigma stays beside a heavy one (a mass fraction of 0.08: the relative rule
    of the training-time prunes would drop it), a blob at 2 sigma goes.  The threshold for a 100 Å box (10^6 cells, 5%)
    is
    5.33 sigma."""
    params, opts, control = _setup([[0.0, 0.0, 0.0], [0.2, 0.0, 0.0], [-0.2, 0.0, 0.0]], sigma_A=0.006)
    control.length_scale = 0.01  # a 100 Å box; the Gaussians 0.6 Å wide, 20 Å apart
    _with_noise(control, pixel_size=0.0025)
    z_unit = float(control.mass_significance(params)[0])  # amplitude 1
    with torch.no_grad():
        params["log_amplitudes"][:] = torch.log(
            torch.tensor([[110.0 / z_unit], [9.0 / z_unit], [2.0 / z_unit]], dtype=torch.float64)
        )
    assert control.significance_threshold() == pytest.approx(5.33, abs=0.01)
    assert control.prune(params, opts, final=True) == 1
    kept = control.mass_significance(params)
    assert params["means"].shape[0] == 2 and float(kept.min()) == pytest.approx(9.0, rel=1e-6)


def test_a_duplicate_is_not_merged_back_in_the_same_step():
    """A duplicate pair starts 1 sigma (0.6 Å) apart, inside the 0.7 Å merge threshold: the
    merge of the same step (and of the next, within one interval) leaves it; a pair still that
    close an interval later is one atom and merges."""
    params, opts, control = _setup([[0.0, 0.0, 0.0]], sigma_A=0.06, warmup_length=0, refine_every=100, merge_every=100)
    control.length_scale = 0.1
    params["means"].grad = torch.zeros_like(params["means"])
    control.state.grad_accum = torch.tensor([[1.0, 0.0, 0.0]])  # a persistent pull
    control.state.grad_count = 1
    counts = control.step_post_backward(params, opts, step=200)
    assert counts["duplicated"] == 1 and params["means"].shape[0] == 2
    gap_A = float((params["means"][0] - params["means"][1]).norm()) / 0.1
    assert gap_A < control.merge_threshold_A
    assert control.merge_step(params, opts, step=200) == 0
    assert params["means"].shape[0] == 2
    assert control.merge_step(params, opts, step=300) == 1  # an interval on, still one atom


def test_added_gaussians_carry_their_mass_fresh_moments_and_are_fresh():
    """DensityControl.add appends Gaussians at the given sites with the given mass and width,
    zero Adam moments, and marks them fresh (neither merged nor pruned for one interval)."""
    params, opts, control = _setup([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]], sigma_A=0.06)
    control.state.step = 700
    added = control.add(params, opts, torch.tensor([[0.2, 0.1, 0.0]], dtype=torch.float64), 0.2, torch.tensor([3.0]))
    assert added == 1 and params["means"].shape[0] == 3
    assert float(_mass(params, control)[2]) == pytest.approx(3.0, rel=1e-9)
    assert float(widths(params, control.min_log_sigma)[2]) == pytest.approx(0.2, rel=1e-9)
    assert float(opts["means"].state[params["means"]]["exp_avg"][2].abs().sum()) == 0.0
    assert control.fresh(3).tolist() == [False, False, True]


def test_discovery_level_drops_with_many_atoms_and_never_exceeds_the_family_wise_one():
    """Benjamini-Hochberg over a 100 Å box (10^6 cells of 1 Å^3) at rate 0.001: one Gaussian
    at 4.5 sigma (P = 3.4e-6 > 0.001 / 10^6) is judged at the family-wise 5.33; among 5,000
    atoms at 4.5 sigma (P = 3.4e-6 <= 0.001 x 5,000 / 10^6 = 5e-6) it is kept, and 500 noise
    Gaussians at 2 sigma beside them do not pull the level down to themselves."""
    _, _, control = _setup([[0.0, 0.0, 0.0]])
    control.length_scale = 0.01
    fw = control.significance_threshold()
    assert control.discovery_threshold(torch.tensor([4.5])) == pytest.approx(fw)
    many = torch.cat([torch.full((5000,), 4.5), torch.full((500,), 2.0)])
    assert control.discovery_threshold(many) == pytest.approx(4.5)
    assert control.discovery_threshold(torch.full((5000,), 30.0)) == pytest.approx(fw)  # capped at family-wise


def test_a_weak_atom_a_bond_away_is_not_merged_into_its_neighbour():
    """A cubic grid of atoms 2.5 Å apart (their shortest bond, read from them), 0.7 Å wide and 6
    sigma strong (Au at noise 500), with one weak atom among them at 3.65 sigma and a weak
    fragment 1.2 Å from an atom along the wedge.  The chi-square test alone cannot resolve the
    weak atom from its neighbours 2.5 Å away; two atoms are never closer than the bond, so the
    unresolved merge takes only the fragment and leaves the weak atom where it is (for the
    prune to judge)."""
    grid = [[0.025 * i, 0.025 * j, 0.025 * k] for i in range(3) for j in range(3) for k in range(3)]
    params, opts, control = _setup(grid + [[0.0, 0.0, 0.012]], sigma_A=0.007, min_sigma_A=0.01)
    control.length_scale = 0.01
    dirs = _tilt_series_dirs()
    _with_noise(control, pixel_size=0.0025, n_views=len(dirs), view_dirs=dirs)
    control.efficiency = math.pi / 2
    z_unit = float(control.mass_significance(params)[0])
    with torch.no_grad():
        params["log_amplitudes"][:] = math.log(6.0 / z_unit)
        params["log_amplitudes"][13] = math.log(3.65 / z_unit)  # the middle atom: weak
        params["log_amplitudes"][27] = math.log(3.65 / z_unit)  # the fragment, 1.2 Å from atom 0
    z = control.mass_significance(params)
    weak = z < control.significance_threshold()
    assert weak.tolist() == [i in (13, 27) for i in range(28)]
    untested = control.unresolved_pairs(params, torch.ones(28, dtype=torch.bool), weak)
    assert any(13 in pair for pair in untested.tolist())  # the test alone would merge it
    assert control.shortest_bond(params["means"], ~weak) == pytest.approx(0.025, rel=1e-12)
    assert control.merge_unresolved(params, opts) == 1  # the fragment only
    assert params["means"].shape[0] == 27
    assert (
        float((params["means"] - torch.tensor([0.025, 0.025, 0.025], dtype=torch.float64)).norm(dim=-1).min()) < 1e-12
    )


def _series_axes(dirs):
    """(V, 2, 3) detector axes (rows along the tilt axis y, columns across) of beam directions ``dirs``."""
    rows = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64).expand(len(dirs), 3)
    cols = torch.stack([dirs[:, 2], torch.zeros(len(dirs), dtype=torch.float64), -dirs[:, 0]], dim=1)
    return torch.stack([rows, cols], dim=1)


@pytest.mark.parametrize("truth", ["one atom", "two atoms"])
def test_likelihood_change_matches_the_pixel_chi_square_and_tells_a_split_atom_from_two(truth):
    """An Au-like atom (0.6 Å wide) seen in 47 views at -70:3:70 degrees, 0.25 Å pixels, with
    Gaussian noise; the model holds two Gaussians 1.5 Å apart along the missing wedge (the beam
    at zero tilt), each with half the mass.  Against the data of one atom the change of the
    data's chi-square on merging them (computed from the residual's correlations and the
    merge's energy) is negative: the data prefer one Gaussian.  Against two atoms 1.5 Å apart it
    is far above the merge level; finalize merges the first pair and keeps the second.  Either
    way the change equals the float64 pixel sum
    ``sum w [(r + p - s)^2 - r^2]`` to 1e-6 of the merge's energy (the energy is an integral;
    on pixels 2.4 times finer than the width the pixel sum of a Gaussian matches it to far
    better than that).  Mid-run (``settle`` without the residual, as the run's checks call it)
    the pair stays two either way: the likelihood test waits for the end.  Three atoms 4 Å away,
    each of the truth's atom mass, make the pair hold one typical atom's mass (one atom) or two
    halves (two atoms at half the mass are still two by the likelihood alone)."""
    from gaussian_atoms_method.physics.projector import project_gaussians

    ls = 0.05  # normalised units per Å: the 16 Å field inside the volume
    dirs = _tilt_series_dirs()
    axes = _series_axes(dirs)
    coords = (torch.arange(64, dtype=torch.float64) - 31.5) * 0.25 * ls
    pair = [[0.0, 0.0, -0.75 * ls], [0.0, 0.0, 0.75 * ls]]
    others = [[4.0 * ls, 0.0, 0.0], [-4.0 * ls, 0.0, 0.0], [0.0, 4.0 * ls, 0.0]]
    params, opts, control = _setup(pair + others, sigma_A=0.6 * ls, amplitude=1.0 / ls)  # projected peak 1.5
    with torch.no_grad():
        params["log_amplitudes"][2:] += math.log(2.0)  # whole atoms: the pair holds one atom's mass
    control.length_scale = ls
    _with_noise(control, read_var=0.01, pixel_size=0.25 * ls, n_views=len(dirs), view_dirs=dirs)
    sig, amp = widths(params, control.min_log_sigma).detach(), amplitudes(params).detach()
    model = project_gaussians(params["means"].detach(), sig, amp, axes, coords, coords)
    if truth == "one atom":
        atoms = torch.cat([torch.zeros(1, 3, dtype=torch.float64), params["means"].detach()[2:]])
        clean = project_gaussians(atoms, sig[1:], torch.cat([2.0 * amp[:1], amp[2:]]), axes, coords, coords)
    else:
        clean = model
    data = clean + 0.1 * torch.randn(clean.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    residual, weight = data - model, 1.0 / 0.01

    def correlations(means, sigmas):
        images = torch.stack(
            [
                project_gaussians(m[None], s[None], torch.ones(1, dtype=torch.float64), axes, coords, coords)
                for m, s in zip(means, sigmas)
            ]
        )
        return (images * residual * weight).sum(dim=(1, 2, 3)).numpy()

    change = control.likelihood_change(params, np.array([[0, 1]]), correlations)[0]
    # equal masses and widths
    merged = project_gaussians(torch.zeros(1, 3, dtype=torch.float64), sig[:1], 2.0 * amp[:1], axes, coords, coords)
    pair_model = project_gaussians(params["means"].detach()[:2], sig[:2], amp[:2], axes, coords, coords)
    pixel = float((weight * ((residual + pair_model - merged) ** 2 - residual**2)).sum())
    energy = float((weight * (pair_model - merged) ** 2).sum())
    assert change == pytest.approx(pixel, abs=1e-6 * energy)
    if truth == "one atom":
        assert change < 0
    else:
        from scipy.stats import chi2

        assert change > chi2.isf(control.false_alarm_rate / control.cells(), df=5)
    assert control.settle(params, opts) == 0 and params["means"].shape[0] == 5
    # finalize with the residual: the split atom becomes one Gaussian with the whole mass at the
    # pair's centre; the two atoms stay two.
    total = float(_mass(params, control).sum())
    control.finalize(params, opts, correlations=correlations)
    assert params["means"].shape[0] == (4 if truth == "one atom" else 5)
    assert float(_mass(params, control).sum()) == pytest.approx(total, rel=1e-9)
    if truth == "one atom":
        assert float(params["means"].detach().norm(dim=1).min()) < 1e-12  # at the pair's centre of mass


def _jittered_lattice(rng) -> np.ndarray:
    """(343, 3) a 7 x 7 x 7 lattice 2.5 Å apart (in Å), each atom moved by 0.05 Å RMS."""
    lattice = np.stack(np.meshgrid(*[np.arange(-3, 4)] * 3, indexing="ij"), -1).reshape(-1, 3) * 2.5
    return lattice + 0.05 * rng.normal(size=lattice.shape)


def _lattice_control(lattice: np.ndarray):
    """Params, optimisers and a density control for ``lattice`` (Å) at a length scale of 0.01,
    each Gaussian 0.6 Å wide, the noise and the limited tilts' beam directions set."""
    params, opts, control = _setup(lattice * 0.01, sigma_A=0.006, min_sigma_A=0.01)
    control.length_scale = 0.01
    _with_noise(control, read_var=1e-9, pixel_size=0.003, n_views=47, view_dirs=_tilt_series_dirs())
    return params, opts, control


def test_a_gaussian_holding_two_atoms_is_split_along_the_missing_wedge():
    """A lattice of 343 atoms 2.5 Å apart in which one Gaussian, 30% wider, holds two atoms'
    mass (two atoms along the beam, as the fit of a thick particle leaves them): it is split
    into two of half its mass and the typical width, the material's shortest distance apart
    (read from the atoms: 2.2-2.5 Å) along z, the axis the limited tilts about y see worst;
    no single atom is touched, and only once a run."""
    rng = np.random.default_rng(2)
    lattice = _jittered_lattice(rng)
    params, opts, control = _lattice_control(lattice)
    heavy = 171  # the lattice's centre
    with torch.no_grad():
        params["log_sigmas"][heavy] = math.log(0.0078)
        params["log_amplitudes"][heavy] = math.log(2.0 / 1.3**3)  # twice the mass of the others
    total = float(_mass(params, control).detach().sum())
    distance, _ = control.shortest_distance(params)
    assert control.split_heavy_gaussians(params, opts) == 1
    assert params["means"].shape[0] == 344
    pair = params["means"].detach()[[heavy, 343]].numpy()
    offset = (pair[0] - pair[1]) / 0.01
    # -70:3:68 is not quite symmetric: the beams' mean axis leans 1 degree from z.
    assert np.linalg.norm(offset) == pytest.approx(distance / 0.01, rel=1e-9) and abs(offset[2]) / np.linalg.norm(
        offset
    ) > math.cos(math.radians(2.0))
    assert 2.2 <= distance / 0.01 <= 2.5
    assert float(_mass(params, control).detach().sum()) == pytest.approx(total, rel=1e-9)
    assert widths(params, control.min_log_sigma)[[heavy, 343]].detach().numpy() == pytest.approx(
        [0.006, 0.006], rel=1e-9
    )
    assert opts["means"].state[params["means"]]["exp_avg"].shape == (344, 3)
    assert control.split_heavy_gaussians(params, opts) == 0  # once a run


def test_a_gaussian_with_part_of_a_neighbour_is_split_where_the_single_atoms_scatter_little():
    """The same lattice with the single atoms' masses scattered by 10% (as a fit leaves them): a
    Gaussian holding an atom and a third of its neighbour (1.33 typical masses, below the 1.5
    ceiling) lies beyond a single atom's 95% range (1 + 1.96 x 0.1) and is split; the single atoms,
    the heaviest of them included, are not.  With the masses spread as wide as two species' the
    ceiling holds: 1.33 is left whole."""
    rng = np.random.default_rng(3)
    lattice = _jittered_lattice(rng)
    for scatter, split in ((0.1, 1), (0.5, 0)):
        params, opts, control = _lattice_control(lattice)
        worth = np.clip(1.0 + scatter * rng.standard_normal(len(lattice)), 0.2, 1.0 + min(1.5 * scatter, 0.45))
        worth[171] = 1.33
        with torch.no_grad():
            params["log_amplitudes"][:, 0] += torch.log(torch.as_tensor(worth, dtype=params["log_amplitudes"].dtype))
        assert split_worth(control.atoms_worth(params)) == pytest.approx(min(1.5, 1.0 + 1.96 * scatter), abs=0.05)
        assert control.split_heavy_gaussians(params, opts) == split
        assert params["means"].shape[0] == 343 + split


def test_a_gaussian_wider_than_one_atom_is_split_whatever_its_mass():
    """Masses spread as three elements' are (0.2-1.45 typical atoms: two light atoms along the beam
    weigh what one middle atom does), the widths scattered by 2% as a fit leaves them: a Gaussian
    of a typical mass but 30% wider than the rest lies beyond the width any single atom reaches
    among 343 (:func:`split_width`) and is split along the beam; no single atom is, the widest
    and the heaviest of them included."""
    rng = np.random.default_rng(5)
    lattice = _jittered_lattice(rng)
    params, opts, control = _lattice_control(lattice)
    worth = np.clip(1.0 + 0.5 * rng.standard_normal(len(lattice)), 0.2, 1.45)
    sigma = 0.006 * (1.0 + 0.02 * rng.standard_normal(len(lattice)))
    sigma[171] = 0.0078
    with torch.no_grad():
        params["log_sigmas"][:, 0] = torch.log(torch.as_tensor(sigma, dtype=params["log_sigmas"].dtype))
        amplitude = worth * (0.006 / sigma) ** 3  # each Gaussian's mass its worth in typical atoms
        amplitude[171] = (0.006 / 0.0078) ** 3
        params["log_amplitudes"][:, 0] += torch.log(torch.as_tensor(amplitude, dtype=params["log_amplitudes"].dtype))
    assert split_worth(control.atoms_worth(params)) == pytest.approx(1.5)
    widest_single = float(np.sort(sigma)[-2])
    assert widest_single < split_width(torch.as_tensor(sigma)) < 0.0078
    assert control.split_heavy_gaussians(params, opts) == 1
    assert params["means"].shape[0] == 344
    offset = (params["means"].detach()[171] - params["means"].detach()[343]).numpy()
    assert abs(offset[2]) / np.linalg.norm(offset) > math.cos(math.radians(2.0))


def test_settling_mid_run_applies_the_final_prune_but_spares_fresh_additions():
    """``settle`` (the final rules mid-run): a noise blob at 2 sigma goes, an atom at 110 stays,
    and a Gaussian a residual search added this interval (as faint) is left its interval; what
    is left of that search is counted by ``descendants``."""
    params, opts, control = _setup([[0.0, 0.0, 0.0], [0.2, 0.0, 0.0]], sigma_A=0.006)
    control.length_scale = 0.01
    _with_noise(control, pixel_size=0.0025)
    z_unit = float(control.mass_significance(params)[0])
    with torch.no_grad():
        params["log_amplitudes"][:] = torch.log(torch.tensor([[110.0 / z_unit], [2.0 / z_unit]], dtype=torch.float64))
    control.state.step = 700
    control.add(
        params,
        opts,
        torch.tensor([[-0.2, 0.0, 0.0]], dtype=torch.float64),
        0.006,
        _mass(params, control)[1:2].detach().clone(),
    )
    assert control.descendants(700) == 1
    assert control.settle(params, opts) == 1 and params["means"].shape[0] == 2
    assert control.descendants(700) == 1 and control.descendants(0) == 0


def test_an_addition_merged_into_an_atom_from_before_the_search_is_not_left_of_the_search():
    """Two additions at step 700: one 0.1 Å from an atom (0.7 Å merge threshold), one 3 Å from
    both atoms. After the merge the first holds an atom from before the search, so only the
    second is what the search found; a heavy atom split in two leaves its new half as the
    search's, and the halves joined again leave none."""
    params, opts, control = _setup([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    control.state.step = 700
    masses = _mass(params, control)[:2].detach().clone()
    assert control.add(params, opts, torch.tensor([[0.1, 0.0, 0.0], [1.5, 3.0, 0.0]], dtype=torch.float64), 0.6, masses)
    assert control.descendants(700) == 2
    assert control.merge(params, opts) == 1 and params["means"].shape[0] == 3
    assert control.descendants(700) == 1
    control.state.step = 900
    n = params["means"].shape[0]
    control.remap(params, opts, *duplicate_remap(n, torch.tensor([0])))
    control.state.born[n:] = control.state.founded[n:] = 900  # as a split marks its new half
    assert control.descendants(900) == 1 and control.descendants(700) == 1
    assert control.merge(params, opts) == 1
    assert control.descendants(900) == 0 and control.descendants(700) == 1


def test_a_weak_addition_still_gaining_mass_holds_the_final_rules_back():
    """A residual search's addition at 2 sigma beside an atom (white noise: one standard
    deviation for any mass): unsettled at the first check after the search (nothing to compare),
    settled while it holds its mass, unsettled once it gains 3 standard deviations while under
    the family-wise level (5.33), settled again when it gains while over it."""
    params, opts, control = _setup([[0.0, 0.0, 0.0]], sigma_A=0.006)
    control.length_scale = 0.01
    _with_noise(control, pixel_size=0.0025)
    z_unit = float(control.mass_significance(params)[0])
    with torch.no_grad():
        params["log_amplitudes"][:] = math.log(110.0 / z_unit)
    control.state.step = 700
    control.add(
        params, opts, torch.tensor([[-0.2, 0.0, 0.0]], dtype=torch.float64), 0.006, _mass(params, control)[:1] * 2 / 110
    )
    control.state.searched_at = 700
    assert float(control.mass_significance(params)[1]) == pytest.approx(2.0, rel=1e-6)
    assert not control.additions_settled(params)
    assert control.additions_settled(params)
    for z, settled in ((5.0, False), (5.0, True), (20.0, True)):
        with torch.no_grad():
            params["log_amplitudes"][1] = math.log(z / z_unit)
        assert control.additions_settled(params) == settled


def test_the_worth_a_run_must_settle_is_that_of_the_gaussians_in_the_reported_field():
    """Three equal Gaussians, the third beyond a film's reported field (inside the volume): it
    holds an atom's worth but none the convergence test counts; the others keep theirs."""
    params, _, control = _setup([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.4, 0.0, 0.0]], sigma_A=0.06)
    control.length_scale, control.field_half_extent = 0.1, (0.2, 0.2, 0.2)
    worth = control.atoms_worth(params)
    assert bool(control.inside(params["means"].detach()).all())
    torch.testing.assert_close(control.counted_worth(params), worth * torch.tensor([1.0, 1.0, 0.0], dtype=worth.dtype))
    assert float(worth[2]) > 0


def test_a_gaussian_wider_than_an_atom_is_imaged_counts_no_atom_the_run_must_settle():
    """Twenty atoms of 0.60-0.62 Å and one Gaussian of 1.2 Å (material no atom explains, widening
    towards the widest an atom can be): it holds mass, but none the convergence test counts."""
    means = [[0.02 * i - 0.2, 0.0, 0.0] for i in range(21)]
    params, _, control = _setup(means, sigma_A=0.06)
    control.length_scale = 0.1
    with torch.no_grad():
        params["log_sigmas"][:20] += torch.linspace(0.0, 0.03, 20)[:, None]
        params["log_sigmas"][20] = math.log(0.12)
    counted, worth = control.counted_worth(params), control.atoms_worth(params)
    assert bool((counted[:20] == worth[:20]).all()) and float(counted[20]) == 0.0 and float(worth[20]) > 0


def test_on_a_film_only_a_gaussian_leaving_above_the_detector_is_named_a_possible_lost_atom():
    """A film's volume reaches beyond the detector across the tilt axis (its field is the
    detector); nothing beyond the field is reported, so an atom-like Gaussian that leaves the
    volume there loses no atom and is not named, while one that leaves along the beam above the
    detector is, as mass beyond the volume's depth (a support, a surface layer or a thicker film),
    not as a geometry to check."""
    params, opts, control = _setup([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [0.0, 0.0, 0.7], [1.7, 0.0, 0.0]], sigma_A=0.06)
    control.length_scale = 0.1
    control.half_extent, control.field_half_extent = (1.5, 0.5, 0.5), (0.5, 0.5, 0.5)
    assert control.prune(params, opts) == 2
    line = control.report()[0]
    assert line.startswith("2 Gaussians left the reconstruction volume")
    assert "1 of them atom-like above the detector" in line
    # it left through the film's faces along the beam, the cube's depth: no geometry to check
    assert "beyond the volume's depth along the beam (5 Å either side" in line and "centre_px" not in line
