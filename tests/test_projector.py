"""The projector against independent computations of the same line integrals."""

import math

import numpy as np
import pytest
import torch
from scipy import integrate

from gaussian_atoms_method.geometry import detector_axes_from_tilts, pixel_centres, project_volume
from gaussian_atoms_method.projector import gaussian_mass, project_gaussians


def _project(means, sigmas, amps, angles, n_pixels, pixel_size, tilt_axis="y", dtype=torch.float64):
    axes = torch.tensor(detector_axes_from_tilts(angles, tilt_axis), dtype=dtype)
    coords = torch.tensor(pixel_centres(n_pixels, pixel_size), dtype=dtype)
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=dtype)
    return project_gaussians(t(means), t(sigmas), t(amps), axes, coords, coords)


def test_matches_quadrature_along_rays():
    """Each pixel is the integral of the 3D Gaussian along the beam through its centre."""
    rng = np.random.default_rng(1)
    means = rng.uniform(-2, 2, size=(3, 3))
    sigmas = np.array([0.4, 0.6, 0.9])
    amps = np.array([1.0, 2.5, 0.7])
    angles = np.array([-63.0, 0.0, 27.5])
    n, px = 24, 0.3
    img = _project(means, sigmas, amps, angles, n, px).numpy()
    axes = detector_axes_from_tilts(angles)
    coords = pixel_centres(n, px)

    def density(r):
        d2 = ((r[None, :] - means) ** 2).sum(1)
        return float((amps * np.exp(-d2 / (2 * sigmas**2))).sum())

    worst = 0.0
    for v in range(len(angles)):
        for i, j in [(12, 12), (5, 17), (20, 3), (11, 14)]:
            origin = coords[i] * axes[v, 0] + coords[j] * axes[v, 1]
            val, _ = integrate.quad(lambda t: density(origin + t * axes[v, 2]), -15, 15, epsabs=1e-13, epsrel=1e-12, limit=200)
            worst = max(worst, abs(img[v, i, j] - val) / max(abs(val), 1e-12))
    # float64 analytic vs adaptive quadrature: both essentially exact.
    assert worst < 1e-8


def test_total_mass():
    """Image sum x pixel area = sum of amplitude (2 pi sigma^2)^(3/2) when the detector holds the atoms."""
    means = np.array([[0.3, -0.2, 0.5], [-1.0, 0.8, -0.4]])
    sigmas = np.array([0.5, 0.7])
    amps = np.array([3.0, 1.2])
    px = 0.1
    img = _project(means, sigmas, amps, [0.0, 41.0, -77.0], 160, px)
    expected = gaussian_mass(torch.tensor(sigmas), torch.tensor(amps)).sum().item()
    # Riemann sum of a Gaussian sampled at px << sigma is exact to far below 1e-9.
    np.testing.assert_allclose(img.sum(dim=(1, 2)).numpy() * px**2, expected, rtol=1e-9)


def test_partly_off_detector():
    """A Gaussian centred on the detector edge keeps exactly the half that falls on it."""
    px, n = 0.1, 60
    edge = pixel_centres(n, px)[0]  # centre of the first row of pixels
    img = _project([[edge, 0.0, 0.0]], [0.5], [1.0], [0.0], n, px)
    full = gaussian_mass(torch.tensor([0.5]), torch.tensor([1.0])).item()
    # Rows at and beyond the edge: half the mass plus half of the edge row (midpoint rule).
    edge_row = img[0, 0].sum().item() * px**2
    np.testing.assert_allclose(img.sum().item() * px**2, full / 2 + edge_row / 2, rtol=1e-6)
    # And the peak sits on the first row.
    assert img[0].argmax().item() // n == 0


@pytest.mark.parametrize("tilt_axis", ["y", "x"])
def test_matches_voxelised_rotate_and_sum(tilt_axis):
    """Independent path: voxelise the Gaussians, rotate with scipy, sum along the beam."""
    px, n = 0.2, 64
    means = np.array([[1.5, -0.8, 2.0], [-2.2, 1.1, -1.3], [0.4, 2.5, 0.0]])
    sigmas = np.array([0.45, 0.6, 0.5])
    amps = np.array([1.0, 0.6, 1.4])
    c = pixel_centres(n, px)
    X, Y, Z = np.meshgrid(c, c, c, indexing="ij")
    vol = np.zeros((n, n, n))
    for m, s, a in zip(means, sigmas, amps):
        vol += a * np.exp(-((X - m[0]) ** 2 + (Y - m[1]) ** 2 + (Z - m[2]) ** 2) / (2 * s * s))
    for angle in (0.0, 35.0, -60.0):
        ref = project_volume(vol, angle, tilt_axis, order=3) * px
        ours = _project(means, sigmas, amps, [angle], n, px, tilt_axis)[0].numpy()
        # Cubic-spline rotation of a 2.5-voxel-wide Gaussian is accurate to about 1% of the peak.
        assert np.abs(ours - ref).max() < 0.01 * ours.max(), (angle, np.abs(ours - ref).max() / ours.max())
        # And the opposite sense of rotation is clearly wrong (the test can tell signs apart).
        if angle != 0.0:
            wrong = _project(means, sigmas, amps, [-angle], n, px, tilt_axis)[0].numpy()
            assert np.abs(wrong - ref).max() > 0.2 * ours.max()


def test_gradcheck_float64():
    torch.manual_seed(0)
    means = (torch.rand(4, 3, dtype=torch.float64) - 0.5).requires_grad_()
    sigmas = (0.2 + 0.1 * torch.rand(4, dtype=torch.float64)).requires_grad_()
    amps = torch.rand(4, dtype=torch.float64).requires_grad_()
    axes = torch.tensor(detector_axes_from_tilts([10.0, -50.0]))
    coords = torch.tensor(pixel_centres(9, 0.12))
    assert torch.autograd.gradcheck(lambda m, s, a: project_gaussians(m, s, a, axes, coords, coords), (means, sigmas, amps))


def test_shape_errors():
    axes = torch.tensor(detector_axes_from_tilts([0.0]))
    c = torch.zeros(4, dtype=torch.float64)
    with pytest.raises(ValueError, match="means"):
        project_gaussians(torch.zeros(3, 2, dtype=torch.float64), torch.ones(3), torch.ones(3), axes, c, c)
    with pytest.raises(ValueError, match="sigmas"):
        project_gaussians(torch.zeros(3, 3, dtype=torch.float64), torch.ones(2), torch.ones(3), axes, c, c)
