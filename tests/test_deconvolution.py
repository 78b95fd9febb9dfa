"""The start's step 6 (:mod:`gaussian_atoms_method.atoms.deconvolution`), rule by rule on
constructed cases; the step on a simulated carbon sphere is in ``test_initialise.py``."""

import numpy as np
from scipy import ndimage

from gaussian_atoms_method.atoms.deconvolution import (
    decoy_level,
    fit_amplitudes,
    matched_response,
    peak_sharpness,
    remainder_sites,
    subvoxel_peaks,
)
from gaussian_atoms_method.atoms.point_response import backprojected_atom, peak_normalised
from gaussian_atoms_method.harness.simulate import parse_tilts


def _gaussian_blob(shape, centre, sigma_vox):
    grid = np.indices(shape, dtype=np.float64)
    return np.exp(-sum((g - c) ** 2 for g, c in zip(grid, centre)) / (2 * sigma_vox**2))


def test_subvoxel_peak_of_a_parabola_is_exact():
    """A field quadratic about (10.3, 9.8, 10.45) along each axis: the three-point parabola
    gives its peak to rounding."""
    grid = np.indices((21, 21, 21), dtype=np.float64)
    field = 100.0 - (grid[0] - 10.3) ** 2 - 2 * (grid[1] - 9.8) ** 2 - 0.5 * (grid[2] - 10.45) ** 2
    np.testing.assert_allclose(subvoxel_peaks(field, np.array([[10, 10, 10]])), [[10.3, 9.8, 10.45]], atol=1e-12)


def test_joint_fit_recovers_amplitudes_of_overlapping_responses():
    """Three responses (a 1.2-voxel Gaussian) 2 voxels apart, so each peak holds a share of its
    neighbours': read at the peaks the amplitudes are 14-43% off; the joint least-squares fit
    recovers 3, 1 and 2 to 1e-6 and the model equals the field (trilinear placement of
    integer positions is exact)."""
    response, centre = peak_normalised(_gaussian_blob((15, 15, 15), (7, 7, 7), 1.2))
    positions = np.array([[10.0, 10.0, 10.0], [10.0, 12.0, 10.0], [12.0, 10.0, 10.0]])
    truth = np.array([3.0, 1.0, 2.0])
    field = sum(a * _gaussian_blob((24, 24, 24), p, 1.2) for a, p in zip(truth, positions))
    read = field[tuple(positions.astype(int).T)]
    assert np.max(np.abs(read - truth) / truth) > 0.1
    amplitudes, model = fit_amplitudes(field, positions, response, centre, iterations=20)
    np.testing.assert_allclose(amplitudes, truth, rtol=1e-6)
    np.testing.assert_allclose(model, field, atol=1e-5)


def test_decoy_level_keeps_what_the_decoys_do_not_match():
    """Five sites stand 7-9 high, the error's maxima 3-5 on both sides.  The level is the lowest
    height where the decoys number at most the rate times the sites: at 0.25 that is 5 (one
    decoy above it against six sites, one of them error), at 0.1 it is 7 (the five atoms
    alone); with no decoys every site is kept; with no sites, or the error alone, nothing."""
    sites = np.array([9.0, 8.5, 8.0, 7.5, 7.0, 5.0, 4.5, 4.0, 3.5, 3.0])
    decoys = np.array([5.1, 4.6, 4.1, 3.6, 3.1])
    assert decoy_level(sites, decoys, 0.25) == 5.0
    assert decoy_level(sites, decoys, 0.1) == 7.0
    assert decoy_level(sites, np.zeros(0), 0.25) == 3.0
    assert decoy_level(np.zeros(0), decoys, 0.25) == np.inf
    assert decoy_level(sites[5:], decoys, 0.25) == np.inf  # the error alone: nothing kept


def test_remainder_sites_finds_the_atom_without_a_candidate():
    """Four blobs; candidates on three of them.  The fourth, 4.5 voxels from one (a shoulder
    of it after filtering), is the one site the remainder shows; with all four as candidates,
    none."""
    sigma = 1.5
    response, centre = peak_normalised(_gaussian_blob((17, 17, 17), (8, 8, 8), sigma))
    atoms = np.array([[12, 12, 12], [12, 16, 12], [20, 12, 14], [12, 12, 16.5]])
    field = sum(_gaussian_blob((32, 32, 32), p, sigma) for p in atoms)
    sites = remainder_sites(field, atoms[:3].astype(int), response, centre, 1.0, 2.0, 0.05)
    assert len(sites) == 1 and np.linalg.norm(sites[0] - atoms[3]) <= 1.0
    assert len(remainder_sites(field, np.rint(atoms).astype(int), response, centre, 1.0, 2.0, 0.05)) == 0


def test_matched_response_reads_the_atom_width():
    """An atom of 0.6 Å back-projected through the limited tilts at 0.32 Å pixels: the
    width read from its pixel-scale Laplacian's peak sharpness is 0.6 Å to 0.03 Å (measured
    0.576: the blur identity is exact for continuous images, and the narrow 0.3 Å atom is
    sampled at under one pixel; a tenth of a pixel is what step 6 can tell apart)."""
    angles = parse_tilts("-72:4:72")
    shape = (len(angles), 64, 64)

    def sharp(v):
        return -ndimage.gaussian_laplace(v, 1.0)

    atom = backprojected_atom(shape, angles, 0.32, 0.6, half_width_A=8.0).data
    field = sharp(atom)
    peak = np.array([np.unravel_index(int(np.argmax(field)), field.shape)])
    narrow = backprojected_atom(shape, angles, 0.32, 0.3, half_width_A=8.0).data
    _, _, width = matched_response(narrow, 0.3, 0.32, sharp, float(peak_sharpness(field, peak)[0]))
    assert abs(width - 0.6) < 0.03


def test_the_fit_on_a_device_is_the_hosts():
    """fit_amplitudes_on_device (the GPU's path, run here on the CPU in torch) gives the host's
    amplitudes and model to float32 rounding, and remainder_sites the same sites from a tensor."""
    import torch

    from gaussian_atoms_method.atoms.deconvolution import fit_amplitudes, fit_amplitudes_on_device, remainder_sites

    rng = np.random.default_rng(5)
    response = np.exp(-0.5 * np.sum((np.indices((9, 9, 9)) - 4.0) ** 2, axis=0) / 1.2**2).astype(np.float32)
    positions = rng.uniform(4, 27, size=(40, 3))
    field = np.zeros((33, 31, 29), dtype=np.float32)
    for p, a in zip(positions, rng.uniform(0.5, 2.0, 40)):
        field += a * np.exp(
            -0.5 * np.sum((np.indices(field.shape) - p[:, None, None, None]) ** 2, axis=0) / 1.2**2
        ).astype(np.float32)
    field += 0.01 * rng.standard_normal(field.shape).astype(np.float32)
    a_host, m_host = fit_amplitudes(field, positions, response, (4, 4, 4), iterations=3)
    a_dev, m_dev = fit_amplitudes_on_device(torch.as_tensor(field), positions, response, (4, 4, 4), iterations=3)
    np.testing.assert_allclose(a_dev, a_host, rtol=1e-4, atol=1e-4 * np.abs(a_host).max())
    np.testing.assert_allclose(m_dev.numpy(), m_host, atol=1e-4 * np.abs(m_host).max())
    indices = np.rint(positions[:30]).astype(np.int64)  # ten atoms left unexplained
    host = remainder_sites(field, indices, response, (4, 4, 4), 1.0, 1.5, 0.1)
    device = remainder_sites(torch.as_tensor(field), indices, response, (4, 4, 4), 1.0, 1.5, 0.1)
    np.testing.assert_array_equal(device, host)
    assert len(host) > 0
