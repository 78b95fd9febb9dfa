"""ADF views through physics the fit does not share (physics/adf.py): abTEM's projected
potentials with ADF contrast, a probe from its optics, scan jitter; and the replica drawn with them."""

import numpy as np
import pytest

pytest.importorskip("abtem")

from gaussian_atoms_method.physics.adf import adf_projections, scan_jitter  # noqa: E402
from gaussian_atoms_method.physics.geometry import detector_axes_of, pixel_centres  # noqa: E402
from gaussian_atoms_method.physics.microscope import (  # noqa: E402
    ProbeOptics,
    aberrated_probe_intensity,
    electron_wavelength_A,
)

PIXEL_A = 0.3


def _centroid(image, centre_A, radius_A, centre_px):
    rows = pixel_centres(image.shape[0], PIXEL_A, centre_px[0])
    cols = pixel_centres(image.shape[1], PIXEL_A, centre_px[1])
    r, c = np.meshgrid(rows, cols, indexing="ij")
    weight = image * (np.hypot(r - centre_A[0], c - centre_A[1]) < radius_A)
    return np.array([(weight * r).sum(), (weight * c).sum()]) / weight.sum()


def test_an_adf_atom_is_drawn_where_it_is_with_its_z_contrast_in_any_view():
    """An atom off the pixel grid, seen in views of any orientation (Euler angles): its image's
    centroid within 3 Å lies on its projected place to 0.002 Å (the window cuts the probe's
    tails a little unevenly), and the view holds its integrated intensity ``Z^1.7`` to 1% (the
    probe's rings and tails beyond a 24 Å field hold 0.5%)."""
    euler = np.array([[0.0, 0.0, 0.0], [10.0, 37.0, -5.0], [-30.0, -62.0, 20.0]])
    axes = detector_axes_of(euler, euler_convention="zyx")
    atom = np.array([[0.37, -0.11, 0.8]])
    views = adf_projections(
        atom,
        ["Ta"],
        np.array([73.0**1.7]),
        axes,
        (81, 79),
        PIXEL_A,
        (40.0, 39.0),
        probe=ProbeOptics(source_fwhm_A=0.7).transfer,
    )
    for v in range(len(axes)):
        place = (atom @ axes[v, :2].T)[0]
        np.testing.assert_allclose(_centroid(views[v], place, 3.0, (40.0, 39.0)), place, atol=2e-3)
        assert views[v].sum() * PIXEL_A**2 == pytest.approx(73.0**1.7, rel=0.01)
        assert views[v].min() > -1e-6 * views[v].max()  # an intensity: the probe band-limits it, no ringing


def test_an_adf_atom_has_a_sharper_core_and_longer_tails_than_a_gaussian():
    """Through a point probe, a Ta atom's image holds more of its intensity beyond 1 Å than the
    Gaussian of the same half-intensity radius holds there (the long tails) and more within a
    quarter of that radius (the sharp core): no width of one Gaussian draws it."""
    views = adf_projections(
        np.zeros((1, 3)), ["Ta"], np.ones(1), detector_axes_of([0.0]), (121, 121), 0.1, (60.0, 60.0), oversample=2
    )[0]
    r = np.hypot(*np.meshgrid(np.arange(121) - 60.0, np.arange(121) - 60.0, indexing="ij")).ravel() * 0.1
    share = views.ravel() / views.sum()
    order = np.argsort(r)
    half = r[order][np.searchsorted(np.cumsum(share[order]), 0.5)]
    sigma = half / np.sqrt(2 * np.log(2))
    gaussian_beyond = lambda radius: np.exp(-(radius**2) / (2 * sigma**2))  # 2D Gaussian's share outside
    assert share[r > 1.0].sum() > 2 * gaussian_beyond(1.0)
    assert share[r <= half / 4].sum() > 1.5 * (1 - gaussian_beyond(half / 4))


def test_the_lighter_element_is_dimmer_by_its_z_contrast_and_atoms_add():
    """Ta beside Fe, 3 Å apart in a 24 Å field: the views are the sum of each atom's own views
    (incoherent imaging is linear in the atoms, to 1e-9 of the peak), and each atom's own view
    holds its ``Z^1.7`` to 1% (the probe's tails beyond the field hold 0.5%)."""
    atoms = np.array([[-1.5, 0.0, 0.0], [1.5, 0.0, 1.0]])
    weights = np.array([73.0, 26.0]) ** 1.7
    axes = detector_axes_of([0.0, 40.0])
    draw = lambda which: adf_projections(
        atoms[which],
        np.array(["Ta", "Fe"])[which],
        weights[which],
        axes,
        (81, 81),
        PIXEL_A,
        (40.0, 40.0),
        probe=ProbeOptics().transfer,
    )
    both, ta, fe = draw([0, 1]), draw([0]), draw([1])
    np.testing.assert_allclose(both, ta + fe, atol=1e-9 * both.max())
    for alone, weight in ((ta, weights[0]), (fe, weights[1])):
        np.testing.assert_allclose(alone.sum(axis=(1, 2)) * PIXEL_A**2, weight, rtol=0.01)


def test_a_probes_transfer_is_its_intensitys_transform_and_the_source_widens_it():
    """ProbeOptics.transfer on a grid is the Fourier transform of the same probe's intensity
    (to 1e-12); a 0.7 Å source lowers the probe's peak and keeps its sum and centre; a 6% halo
    moves intensity far out."""
    optics = ProbeOptics()
    intensity = aberrated_probe_intensity(0.3, size_px=65, wavelength_A=electron_wavelength_A(300.0))
    from_transfer = np.fft.fftshift(np.fft.ifft2(optics.transfer((65, 65), 0.3)).real)
    np.testing.assert_allclose(from_transfer, intensity, atol=1e-12)
    spread = ProbeOptics(source_fwhm_A=0.7).intensity(0.3)
    assert spread.sum() == pytest.approx(1.0) and spread.min() >= 0.0
    assert np.unravel_index(spread.argmax(), spread.shape) == (32, 32)
    assert spread.max() < 0.8 * intensity.max()
    halo = ProbeOptics(halo_fraction=0.06).intensity(0.3)
    r = np.hypot(*np.meshgrid(np.arange(65) - 32.0, np.arange(65) - 32.0, indexing="ij")) * 0.3
    assert halo.sum() == pytest.approx(1.0)
    assert halo[r > 4.0].sum() - intensity[r > 4.0].sum() > 0.015  # a 2 Å Lorentzian: 31% of its 6% out there


def test_scan_jitter_moves_each_line_by_its_own_shift():
    """A ridge down the columns: after the jitter each row's centroid sits at the row's shift
    (to 0.02 px: linear interpolation of a 2 px wide ridge), and a flat view stays flat."""
    cols = np.arange(64, dtype=np.float64)
    ridge = np.broadcast_to(np.exp(-((cols - 31.5) ** 2) / (2 * 2.0**2)), (2, 40, 64)).copy()
    moved, shifts = scan_jitter(ridge, 0.5, np.random.default_rng(3))
    assert shifts.shape == (2, 40) and 0.3 < shifts.std() < 0.7
    centroids = (moved * cols).sum(axis=2) / moved.sum(axis=2)
    np.testing.assert_allclose(centroids - 31.5, shifts, atol=0.02)
    flat, _ = scan_jitter(np.ones((1, 8, 8)), 0.5, np.random.default_rng(0))
    np.testing.assert_allclose(flat, 1.0)


def test_the_replica_draws_adf_atoms_unless_asked_for_gaussians():
    """``replica_of`` through abTEM physics by default: noiseless, through a 0.5 Å Gaussian probe,
    a lone Ta atom off the grid sits at its true place in every view (to 0.005 Å), and its image
    is not the Gaussian replica's (they differ by more than a tenth of the peak)."""
    from dataparsers.tilt_series_format import TiltSeries
    from gaussian_atoms_method.atoms.atom_set import AtomSet
    from gaussian_atoms_method.harness.replica import replica_of

    euler = np.c_[np.zeros(5), np.linspace(-60, 60, 5), np.zeros(5)]
    ramp = np.broadcast_to(np.linspace(1.0, 2.0, 61), (5, 61, 61))  # views that hold no noise
    geometry = TiltSeries(ramp, euler, PIXEL_A, centre_px=(30.0, 30.0), euler_convention="zyx")
    atoms = AtomSet(np.array([[0.37, 0.5, 0.7]]), species=["Ta"])
    adf = replica_of(geometry, atoms, probe="gaussian")
    gauss = replica_of(geometry, atoms, probe="gaussian", potential="gaussian")
    noise = adf.noise.variance(np.ones(1))
    assert np.all(noise < 1e-6)  # the geometry's views hold no noise: the replica is clean
    for v, axes in enumerate(geometry.detector_axes()):
        for place in atoms.positions @ axes[:2].T:
            np.testing.assert_allclose(_centroid(adf.projections[v], place, 2.0, (30.0, 30.0)), place, atol=5e-3)
    assert np.abs(adf.projections - gauss.projections).max() > 0.1 * adf.projections.max()


def test_simulate_draws_a_particle_as_adf_views_through_its_probe():
    """``simulate_tilt_series(..., potential="adf")``: a two-element particle's noiseless views
    hold each atom's ``Z^1.7`` (to 1%: the probe's tails beyond the detector's margin) and are
    symmetric about the detector's centre for a particle symmetric about the tilt centre."""
    from gaussian_atoms_method.atoms.atom_set import AtomSet
    from gaussian_atoms_method.harness.simulate import simulate_tilt_series

    atoms = AtomSet(np.array([[-2.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 0.0, 2.5], [0.0, 0.0, -2.5]]),
                    species=["Pt", "Pt", "Co", "Co"])  # fmt: skip
    sim = simulate_tilt_series(atoms, np.array([-40.0, 0.0, 40.0]), potential="adf", probe="aberrated",
                               noise_std=0.0, margin_A=8.0)  # fmt: skip
    total = 2 * 78.0**1.7 + 2 * 27.0**1.7
    np.testing.assert_allclose(sim.projections.sum(axis=(1, 2)) * sim.pixel_size_A**2, total, rtol=0.01)
    views = sim.projections.astype(np.float64)
    np.testing.assert_allclose(views, views[:, ::-1, ::-1], atol=1e-4 * views.max())


def test_a_light_atom_beside_heavy_ones_is_found_and_named():
    """Ni atoms among Pt atoms, drawn through ADF physics (``Z^1.7``: a Ni atom holds 0.18 of a Pt
    atom's mass), the elements given: every Ni atom is found and named Ni, with no false atom.
    (The training prune once took atoms under 0.25 of a typical atom's mass for noise candidates
    and lost every Ni atom.)  32 atoms on a 2.7 Å lattice, alternating, high dose: the positions
    hold no doubt, only the rule could lose them."""
    import dataclasses

    import gaussian_atoms_method as ga
    from dataparsers.tilt_series_format import TiltSeries
    from gaussian_atoms_method.atoms.atom_set import AtomSet
    from gaussian_atoms_method.atoms.matching import match_atoms
    from gaussian_atoms_method.harness.replica import replica_of

    side = [-4.05, -1.35, 1.35, 4.05]
    grid = np.stack(np.meshgrid(side, side, [-1.35, 1.35], indexing="ij"), -1).reshape(-1, 3)
    species = np.array(["Ni", "Pt"] * 16)
    rng = np.random.default_rng(2)
    geometry = TiltSeries(100.0 + rng.normal(0.0, 1.0, (25, 64, 64)), np.linspace(-70.0, 70.0, 25), 0.3)
    made = replica_of(geometry, AtomSet(grid, species=species), probe="gaussian", seed=2)
    atoms = ga.reconstruct(
        dataclasses.replace(geometry, projections=made.projections), species="Ni,Pt", device="cpu", progress=False
    )
    pi, ti = match_atoms(atoms.positions, grid, 0.75)
    assert len(atoms) == 32 and len(pi) == 32
    assert list(atoms.species[pi]) == list(species[ti])


def test_the_deposited_adf_views_equal_the_exact_ones_far_below_any_noise():
    """Forty atoms of two elements off the pixel grid, in three tilted views, drawn by depositing
    them on a grid four times finer than the detector (cloud in cell, its transfer divided out)
    against each atom's exact phases: the views agree to 0.5% of their peak everywhere and hold
    the same intensity to 1e-5.  Why 0.5%: the probe's highest frequency (2.0 / Å) lies at a sixth
    of the fine grid's sampling frequency at 0.3 Å pixels, where the sharing's aliased images
    weigh about 2% of an atom's spectrum, and the probe's transfer there is near zero; a view
    with a peak-to-noise ratio of 200 (a high dose) holds noise of 0.5% of its peak."""
    rng = np.random.default_rng(3)
    atoms = rng.uniform(-6.0, 6.0, size=(40, 3))
    species = np.where(np.arange(40) % 3 == 0, "Ni", "Pt")
    weights = np.where(species == "Ni", 28.0**1.7, 78.0**1.7)
    axes = detector_axes_of([-50.0, 3.0, 61.0])
    kwargs = dict(probe=ProbeOptics(source_fwhm_A=0.7).transfer)
    exact = adf_projections(atoms, species, weights, axes, (57, 53), PIXEL_A, (28.3, 26.1), **kwargs)
    deposit = adf_projections(
        atoms, species, weights, axes, (57, 53), PIXEL_A, (28.3, 26.1), method="deposit", **kwargs
    )
    assert np.abs(deposit - exact).max() < 5e-3 * exact.max()
    assert deposit.sum() == pytest.approx(exact.sum(), rel=1e-5)
