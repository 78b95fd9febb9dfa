"""The shortest interatomic distance read from the atoms, and the close-pair rule that uses it."""

import math

import numpy as np
import pytest
import torch

from gaussian_atoms_method.atoms.atom_set import read_atoms
from gaussian_atoms_method.atoms.pair_distribution import MIN_ATOMS, shortest_distance
from gaussian_atoms_method.harness.particles import make_particle

AU_NP = "../shared/data/au_np/Au_NP.xyz"


@pytest.mark.parametrize("name, nearest_A", [("carbon", 1.38), ("asi", 2.2), ("apd", 2.5), ("fept", 2.67)])
def test_the_distance_sits_just_below_each_materials_shortest_bond(name, nearest_A):
    """On true structures the onset of g(r)'s first shell lies within 10% below the material's
    shortest nearest-neighbour distance (the kernel's width smooths the edge: 1.40 of 1.38 Å
    for carbon, 2.10 of 2.2 for a-Si), and almost no atom is closer."""
    atoms = make_particle(name, scale=0.35)
    distance, share = shortest_distance(atoms.positions)
    assert 0.9 * nearest_A <= distance <= 1.02 * nearest_A
    assert share <= 0.02


def test_split_atoms_do_not_move_the_distance():
    """Split 10% of the Au particle's atoms into halves 1.2 Å apart: the first shell (12
    neighbours at 2.88 Å) still dominates g(r) and the distance stays within 10% of the bond;
    every half is reported as closer than it (and so are neighbours that a half moved towards)."""
    pytest.importorskip("ase")
    from pathlib import Path

    if not Path(AU_NP).is_file():
        pytest.skip("needs ../shared/data/au_np")
    positions = read_atoms(AU_NP).positions[:3000]
    rng = np.random.default_rng(0)
    split = rng.choice(len(positions), 300, replace=False)
    direction = rng.normal(size=(300, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    halves = np.concatenate(
        [np.delete(positions, split, axis=0), positions[split] + 0.6 * direction, positions[split] - 0.6 * direction]
    )
    distance, share = shortest_distance(halves)
    assert 0.9 * 2.88 <= distance <= 2.88
    assert share >= 600 / len(halves)
    assert shortest_distance(halves[: MIN_ATOMS - 1]) == (math.inf, 1.0)


def _lattice(seed: int) -> np.ndarray:
    """(343, 3) atoms 2.5 Å apart, jittered by 0.05 Å, Å."""
    lattice = np.stack(np.meshgrid(*[np.arange(-3, 4)] * 3, indexing="ij"), -1).reshape(-1, 3) * 2.5
    return lattice + 0.05 * np.random.default_rng(seed).normal(size=lattice.shape)


def _control_over(positions_A: np.ndarray, amplitudes: np.ndarray | None = None):
    """The Gaussians at ``positions_A`` (N, 3), 0.6 Å wide, of ``amplitudes`` (N,) (default 1),
    at 0.01 normalised units per Å, with frozen optimisers and a density control that knows a
    tiny white noise and one view direction: ``(params, optimizers, control)``."""
    from gaussian_atoms_method.density.strategy import DensityControl
    from gaussian_atoms_method.physics.noise import NoiseModel

    n = len(positions_A)
    amplitudes = np.ones(n) if amplitudes is None else np.asarray(amplitudes, dtype=np.float64)
    params = torch.nn.ParameterDict(
        {
            "means": torch.nn.Parameter(torch.tensor(positions_A * 0.01)),
            "log_sigmas": torch.nn.Parameter(torch.full((n, 1), math.log(0.006), dtype=torch.float64)),
            "log_amplitudes": torch.nn.Parameter(torch.tensor(np.log(amplitudes))[:, None]),
        }
    )
    optimizers = {k: torch.optim.Adam([p], lr=0.0) for k, p in params.items()}
    control = DensityControl(length_scale=0.01, max_log_amplitude=50.0, generator=torch.Generator().manual_seed(0))
    control.reset(n)
    control.noise, control.pixel_size, control.n_views = NoiseModel(1e-9, 0.0), 0.003, 40
    control.view_dirs = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    return params, optimizers, control


def test_a_too_close_pair_needs_the_prior_odds_to_stay_two(monkeypatch):
    """Two pairs of an atom and a fragment of 0.4 of its mass (a misfit's leftover) whose merge
    costs the same chi-square, just above the usual level: the one closer than the material's
    shortest distance merges (its level is raised by twice the log prior odds against so close a
    pair), the one farther apart stays two."""
    from scipy.stats import chi2

    from gaussian_atoms_method.density.strategy import DensityControl

    lattice = _lattice(1)
    # a pair 1.2 Å apart, one 2.4 Å (but for the lattice)
    close, far = (
        lattice[0] + [0, 0, 1.2],
        lattice[-1] + [0, 0, 2.4],
    )
    params, optimizers, control = _control_over(np.concatenate([lattice, [close, far]]), np.r_[np.ones(343), 0.4, 0.4])
    n = params["means"].shape[0]
    distance, prior = control.shortest_distance(params)
    assert 2.2 <= distance / 0.01 <= 2.5 and prior(np.array([0.012]))[0] > 5.0  # one pair in 345 atoms is that close
    level = chi2.isf(control.false_alarm_rate / control.cells(), df=5)

    def change(pairs):  # a test pair's merge costs the usual level + 1; any other pair far more
        return np.where((pairs >= n - 2).any(axis=1), level + 1.0, 1e9)

    monkeypatch.setattr(DensityControl, "likelihood_change", lambda self, p, pairs, c: change(pairs))
    removed = control.merge_by_likelihood(params, optimizers, correlations=lambda m, s: None, max_rounds=1)
    assert removed == 1
    left = params["means"].detach().numpy() / 0.01
    assert np.min(np.linalg.norm(left - (lattice[0] + [0, 0, 1.2]), axis=1)) > 0.5  # the close pair became one
    assert np.min(np.linalg.norm(left - (lattice[-1] + [0, 0, 2.4]), axis=1)) < 1e-9  # the far one stayed two


def test_one_atoms_mass_in_one_peak_is_one_atom_whatever_the_likelihood(monkeypatch):
    """Two pairs 1.0 Å apart, Gaussians 0.6 Å wide (one peak), in a lattice of 2.5 Å, both of which
    the likelihood wants as two (a merge would cost 1e9 chi-square: a shape the forward model
    misses): the pair holding 1.2 typical atoms' mass (two halves of 0.6, as a carbon atom split
    along the beam) becomes one at its centre of mass; the pair holding two atoms' mass stays two."""
    from gaussian_atoms_method.density.strategy import DensityControl

    lattice = _lattice(2)
    light_at, heavy_at = lattice[0], lattice[-1]
    halves = [light_at + [0, 0, 0.5], light_at - [0, 0, 0.5], heavy_at + [0, 0, 1.0]]
    amplitudes = np.r_[np.ones(len(lattice) - 1), 0.6, 0.6, 1.0]
    params, optimizers, control = _control_over(np.concatenate([lattice[1:], halves]), amplitudes)
    assert control.shortest_distance(params)[0] / 0.01 > 1.0
    monkeypatch.setattr(DensityControl, "likelihood_change", lambda self, p, pairs, c: np.full(len(pairs), 1e9))
    removed = control.merge_by_likelihood(params, optimizers, correlations=lambda m, s: None)
    assert removed == 1
    left = params["means"].detach().numpy() / 0.01
    assert np.min(np.linalg.norm(left - light_at, axis=1)) < 1e-9  # the halves' centre of mass
    assert np.min(np.linalg.norm(left - (heavy_at + [0, 0, 1.0]), axis=1)) < 1e-9  # two atoms' mass: two
    assert np.min(np.linalg.norm(left - heavy_at, axis=1)) < 1e-9


def test_a_pair_half_a_bond_apart_is_rarer_than_one_just_under_the_onset():
    """A fit that split 3% of an a-Pd particle's atoms into halves 1.0 Å apart reads the split
    halves' share at the onset; following the first shell's low side, a pair 1.0 Å apart is as
    rare as one in the particle's atoms (the shell holds none that close), while one just under
    the onset keeps at least half the measured share.  Where most atoms have their nearest
    neighbour far below the main peak (carbon at scale 0.5: its C-C bonds under the 2.4 Å
    second-neighbour peak) the share stays as measured at every distance."""
    from gaussian_atoms_method.atoms.pair_distribution import first_shell

    positions = make_particle("apd", scale=0.5).positions
    rng = np.random.default_rng(0)
    split = rng.choice(len(positions), 60, replace=False)
    halves = np.concatenate([np.delete(positions, split, axis=0), positions[split], positions[split] + [0.0, 0.0, 1.0]])
    shell = first_shell(halves)
    assert 2.2 <= shell.onset < shell.peak <= 2.9 and shell.share >= 120 / len(halves) and shell.inner_share < 0.5
    f = shell.share_closer(np.array([1.0, shell.onset - 0.01, shell.onset]))
    assert f[0] == pytest.approx(1.0 / len(halves))
    assert 0.5 * shell.share <= f[1] <= shell.share and f[2] == shell.share

    carbon = first_shell(make_particle("carbon", scale=0.5).positions)
    assert carbon.onset > 2.0 and carbon.inner_share > 0.9
    assert np.all(carbon.share_closer(np.array([1.0, 1.4])) == carbon.share)


def test_binned_kernel_density_stays_within_its_binning_bound_of_the_direct_sum():
    """Binning moves each distance by at most half a bin, so each weighted kernel moves by at
    most its weight times the Gaussian's steepest slope (exp(-1/2) / h) times that: the density
    stays within that bound of the direct float64 sum everywhere, and the shell read from the
    a-Pd particle's pair distances is the same."""
    from scipy.spatial import cKDTree

    from gaussian_atoms_method.atoms.pair_distribution import (
        BINS_PER_GRID_STEP,
        GRID_POINTS,
        kernel_density_reference,
        weighted_kernel_density,
    )

    positions = make_particle("apd", scale=0.5).positions
    pairs = cKDTree(positions).query_pairs(5.0, output_type="ndarray")
    d = np.linalg.norm(positions[pairs[:, 0]] - positions[pairs[:, 1]], axis=1)
    w = 1.0 / d**2
    grid = np.linspace(0.0, d.max(), GRID_POINTS)
    for h in (0.01, 0.05, 0.2):
        fast, slow = weighted_kernel_density(d, w, grid, h), kernel_density_reference(d, w, grid, h)
        half_bin = 0.5 * (grid[1] - grid[0]) / BINS_PER_GRID_STEP
        assert np.max(np.abs(fast - slow)) <= math.exp(-0.5) / h * half_bin * w.sum()
        assert np.argmax(fast) == np.argmax(slow)
        onset = lambda density: np.nonzero(density[: np.argmax(density) + 1] < 0.5 * density.max())[0][-1]  # noqa: E731
        assert onset(fast) == onset(slow)


def test_binned_kernel_density_is_the_direct_sum_over_its_bins():
    """The binned density is read as a correlation of the bins' masses with one sampled kernel
    cut KERNEL_WIDTHS bandwidths out (exp(-50) of its peak): it equals the float64 direct sum
    over the occupied bins to rounding, for kernels from a tenth of a bin to wider than all the
    bins (the direct sum's own branch)."""
    from gaussian_atoms_method.atoms.pair_distribution import (
        BINS_PER_GRID_STEP,
        GRID_POINTS,
        kernel_density_reference,
        weighted_kernel_density,
    )

    rng = np.random.default_rng(3)
    d = np.concatenate([rng.normal(2.9, 0.1, 20000), rng.uniform(0.5, 5.8, 5000)])
    w = 1.0 / d**2
    for top in (d.max(), 3.0 * d.max()):
        grid = np.linspace(0.0, top, GRID_POINTS)
        step = (grid[1] - grid[0]) / BINS_PER_GRID_STEP
        mass = np.bincount(np.rint(d / step).astype(np.int64), weights=w)
        occupied = np.nonzero(mass)[0]
        for h in (0.1 * step, 0.01, 0.08, 0.5, 50.0):
            direct = kernel_density_reference(occupied * step, mass[occupied], grid, h)
            assert np.max(np.abs(weighted_kernel_density(d, w, grid, h) - direct)) <= 1e-12 * direct.max()


def test_the_close_packing_has_a_measured_glass_share_of_close_pairs():
    """``apd-close`` holds the close pairs of a measured amorphous Pd particle: about 2% of atoms
    with a neighbour under 2.0 Å and 28% under 2.2 Å.  On 2,000 atoms the shares scatter by
    sqrt(p(1 - p) / n): 0.3% and 1% (binomial), so the bounds allow about three of those."""
    from scipy.spatial import cKDTree

    positions = make_particle("apd-close", scale=0.5).positions
    nearest = cKDTree(positions).query(positions, k=2)[0][:, 1]
    assert 0.01 <= (nearest < 2.0).mean() <= 0.03
    assert 0.25 <= (nearest < 2.2).mean() <= 0.35


def test_two_atoms_mass_a_bond_apart_stays_two_whatever_the_likelihood(monkeypatch):
    """Two pairs 1.46 Å apart (a carbon bond) in a lattice of 2.5 Å, both of which the likelihood
    wants as one (a merge would gain chi-square: through a probe the fit does not share, two
    bonded atoms can fit that way at a low dose): the pair of two halves (one atom's mass) becomes
    one; the pair of two whole atoms stays two, as the hard-core join keeps it (a Gaussian of two
    atoms' mass is one the split proposes again)."""
    from gaussian_atoms_method.density.strategy import DensityControl

    lattice = _lattice(3)
    light_at, heavy_at = lattice[0], lattice[-1]
    pairs = [light_at - [0, 0, 1.46], heavy_at + [0, 0, 1.46]]  # outward from the lattice's corners
    amplitudes = np.r_[np.ones(len(lattice)), 1.0, 1.0]
    amplitudes[0] = 0.5
    amplitudes[-3] = 1.0
    amplitudes[-2] = 0.5  # the first pair: two halves
    params, optimizers, control = _control_over(np.concatenate([lattice, pairs]), amplitudes)
    assert control.shortest_distance(params)[0] / 0.01 > 1.46  # no prior odds against either pair
    monkeypatch.setattr(DensityControl, "likelihood_change", lambda self, p, pairs, c: np.full(len(pairs), -1.0))
    removed = control.merge_by_likelihood(params, optimizers, correlations=lambda m, s: None, max_rounds=1)
    assert removed == 1
    left = params["means"].detach().numpy() / 0.01
    assert np.min(np.linalg.norm(left - (light_at - [0, 0, 0.73]), axis=1)) < 1e-9  # the halves' centre
    assert np.min(np.linalg.norm(left - heavy_at, axis=1)) < 1e-9  # two atoms' mass: two
    assert np.min(np.linalg.norm(left - (heavy_at + [0, 0, 1.46]), axis=1)) < 1e-9
