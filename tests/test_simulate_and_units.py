"""The quick simulator and the paper's normalisation."""

import numpy as np
import pytest
import torch

from gaussian_atoms_method.atoms.atom_set import AtomSet
from gaussian_atoms_method.harness.simulate import (
    MASS_PER_Z,
    gaussian_potential_parameters,
    parse_tilts,
    simulate_gaussian_tilt_series,
    spherical_particle,
)
from gaussian_atoms_method.physics.geometry import detector_axes_from_tilts, pixel_centres
from gaussian_atoms_method.physics.projector import project_gaussians
from gaussian_atoms_method.physics.units import DATA_RANGE, Normalisation


def test_tilt_schemes():
    assert len(parse_tilts("full")) == 181 and parse_tilts("full")[0] == -90
    limited = parse_tilts("limited")
    assert len(limited) == 47 and limited[0] == -70 and limited[-1] == 68
    np.testing.assert_array_equal(parse_tilts("-10:5:10"), [-10, -5, 0, 5, 10])
    np.testing.assert_array_equal(parse_tilts("1,2.5"), [1, 2.5])
    with pytest.raises(ValueError, match="tilts"):
        parse_tilts("sideways")
    with pytest.raises(ValueError, match="empty"):
        parse_tilts("10:1:0")


def test_spherical_particle_is_fcc_and_centred():
    p = spherical_particle("Au", 8.0)
    d = np.linalg.norm(p.positions[:, None] - p.positions[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    assert d.min() == pytest.approx(4.08 / np.sqrt(2), abs=0.01)  # Au fcc nearest neighbour
    assert np.linalg.norm(p.positions, axis=1).max() <= 8.0
    assert set(p.species) == {"Au"}


def test_simulated_mass_and_noise():
    atoms = AtomSet(np.array([[0.0, 0.0, 0.0], [2.0, -1.0, 1.0]]), species=["Au", "Pt"])
    sim = simulate_gaussian_tilt_series(
        atoms, np.array([0.0, 30.0]), pixel_size_A=0.2, detector_pixels=80, noise_std=0.0
    )
    # Blur and projection conserve the integrated potential: MASS_PER_Z x Z per atom.
    expected = MASS_PER_Z * (79 + 78)
    np.testing.assert_allclose(sim.projections.sum(axis=(1, 2)) * 0.2**2, expected, rtol=1e-4)
    noisy = simulate_gaussian_tilt_series(
        atoms, np.array([0.0, 30.0]), pixel_size_A=0.2, detector_pixels=80, noise_std=5.0
    )
    resid = noisy.projections - sim.projections
    assert resid.std() == pytest.approx(5.0, rel=0.03)  # 12,800 samples: 1% standard error
    assert noisy.peak_to_noise == pytest.approx(sim.projections.max() / 5.0, rel=1e-5)


def test_normalisation_round_trip_and_amplitude_units():
    """A Gaussian fitted in normalised units reproduces the physical projection when converted."""
    rng = np.random.default_rng(0)
    proj = rng.uniform(0, 37.0, size=(3, 40, 50))
    norm = Normalisation.for_tilt_series(proj, pixel_size_A=0.3, origin_A=(1.0, 2.0, 3.0))
    assert norm.length_scale == pytest.approx(1 / (50 * 0.3))
    assert norm.data_scale * np.abs(proj).max() == pytest.approx(DATA_RANGE)
    pos = rng.normal(size=(4, 3))
    np.testing.assert_allclose(norm.positions_to_A(norm.positions_from_A(pos)), pos)
    # One Gaussian in normalised units, projected, then scaled back to input units ...
    sig_n, amp_n = 0.02, 500.0
    axes = torch.tensor(detector_axes_from_tilts([20.0]))
    c_n = torch.tensor(pixel_centres(50, 0.3 * norm.length_scale))
    img_n = project_gaussians(
        torch.zeros(1, 3, dtype=torch.float64),
        torch.tensor([sig_n], dtype=torch.float64),
        torch.tensor([amp_n], dtype=torch.float64),
        axes,
        c_n,
        c_n,
    )
    # ... equals the same Gaussian converted to Å and physical amplitude, projected in Å.
    c_A = torch.tensor(pixel_centres(50, 0.3))
    sig_A = float(norm.sigmas_to_A(sig_n))
    amp = float(norm.amplitudes_to_physical(amp_n))
    img_A = project_gaussians(
        torch.zeros(1, 3, dtype=torch.float64),
        torch.tensor([sig_A], dtype=torch.float64),
        torch.tensor([amp], dtype=torch.float64),
        axes,
        c_A,
        c_A,
    )
    torch.testing.assert_close(img_n / norm.data_scale, img_A)
    with pytest.raises(ValueError, match="all zero"):
        Normalisation.for_tilt_series(np.zeros((2, 3, 3)), 0.25)


def test_potential_parameters_scale_with_z():
    s, a = gaussian_potential_parameters(["Fe", "Pt"], 0.4)
    mass = a * (2 * np.pi * s**2) ** 1.5
    np.testing.assert_allclose(mass, MASS_PER_Z * np.array([26, 78]))


def _centroid(img, radius_px=15):
    """Centroid of a radially symmetric peak within a window: unbiased for sharp cores too."""
    i, j = np.unravel_index(np.argmax(img), img.shape)
    ii, jj = np.meshgrid(np.arange(img.shape[0]), np.arange(img.shape[1]), indexing="ij")
    w = np.where((ii - i) ** 2 + (jj - j) ** 2 <= radius_px**2, img, 0.0)
    return np.array([(w * ii).sum(), (w * jj).sum()]) / w.sum()


def test_lobato_is_independent_physics_with_the_same_geometry():
    """abTEM's Lobato projections differ from our Gaussian model (no inverse crime) while the
    atom lands on the same detector position, for off-centre atoms at several tilts."""
    pytest.importorskip("abtem")
    from gaussian_atoms_method.harness.simulate import project_gaussian_potential, project_lobato_potential

    px, n = 0.1, 81  # fine pixels so the sub-pixel peak is well defined
    for position, angle, tilt_axis in [
        ([1.3, -0.7, 0.9], 0.0, "y"),
        ([1.3, -0.7, 0.9], 35.0, "y"),
        ([-0.8, 1.1, -1.4], -60.0, "x"),
    ]:
        atom = AtomSet(np.array([position]), species=["Au"])
        lob = project_lobato_potential(atom, [angle], px, n, tilt_axis)[0]
        gau = project_gaussian_potential(atom, [angle], px, n, 0.35, tilt_axis)[0]
        # Same place: centroids agree to 0.05 pixel (5 pm), far below the 0.75 Å match radius.
        np.testing.assert_allclose(_centroid(lob), _centroid(gau), atol=0.05)
        # Different physics: the Lobato core is much sharper than a 0.35 Å Gaussian.
        assert lob.max() > 2 * gau.max()
        corr = np.corrcoef(lob.ravel(), gau.ravel())[0, 1]
        assert corr < 0.95


def test_film_wider_than_the_field_is_projected_whole_and_cropped():
    """A film seen by a narrower detector: each view is the projection of the whole film on the
    smaller detector (cropping keeps the pixel centres: the same Gaussian projection, float64,
    to 1e-12 of the peak), and the truth holds exactly the atoms above the detector."""
    from gaussian_atoms_method.harness.particles import amorphous_packing
    from gaussian_atoms_method.harness.simulate import simulate_tilt_series

    film = amorphous_packing(0, ("Pd",), 2.5, np.random.default_rng(0), box_A=(30.0, 12.0, 8.0))
    assert np.all(np.abs(film.positions) <= np.array([15.0, 6.0, 4.0]) + 1e-9)
    assert (
        np.linalg.norm(film.positions[:, None] - film.positions[None], axis=-1)[np.triu_indices(len(film), 1)].min()
        > 0.98 * 2.5
    )
    angles = np.array([-60.0, 0.0, 45.0])
    sim = simulate_tilt_series(
        film, angles, potential="gaussian", pixel_size_A=0.5, blur_sigma_A=0.0, noise_std=0.0, field_of_view_A=10.0
    )
    field = sim.projections.shape[-1]
    assert sim.projections.shape == (3, field, field) and abs(field * 0.5 - 10.0) <= 0.5
    half = 0.5 * field * 0.5
    inside = np.all(np.abs(film.positions[:, :2]) <= half, axis=1)
    np.testing.assert_array_equal(sim.truth.positions, film.positions[inside])
    sigmas, amplitudes = gaussian_potential_parameters(film.species, 0.35)
    coords = torch.from_numpy(pixel_centres(field, 0.5))
    direct = project_gaussians(
        torch.from_numpy(film.positions),
        torch.from_numpy(sigmas),
        torch.from_numpy(amplitudes),
        torch.from_numpy(detector_axes_from_tilts(angles, "y")),
        coords,
        coords,
    ).numpy()
    np.testing.assert_allclose(sim.projections, direct, rtol=0, atol=1e-6 * direct.max())


def test_generated_particles_grow_and_cut_ones_refuse_to():
    from gaussian_atoms_method.harness.particles import make_particle

    # Atom count ~ scale^3 for a generated particle (16,000 a-Pd atoms at scale 1); a particle
    # cut from a structure file cannot hold more atoms than the file.
    assert len(make_particle("apd", 1.1).positions) == round(16000 * 1.1**3)
    with pytest.raises(ValueError, match="at most 1"):
        make_particle("au", 1.1)
