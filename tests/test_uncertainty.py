"""Per-atom position precision: the analytic curvature against autograd, and against the
scatter of repeated fits to noisy data (Monte Carlo)."""

import numpy as np
import pytest
import torch

from gaussian_atoms_method.atoms.uncertainty import position_std_A, robust_noise_std
from gaussian_atoms_method.physics.geometry import detector_axes_from_tilts, pixel_centres
from gaussian_atoms_method.physics.projector import project_gaussians

PIXEL_A = 0.25
ANGLES = np.arange(-70.0, 71.0, 10.0)  # 15 views, a missing wedge
AXES = detector_axes_from_tilts(ANGLES)
COORDS = pixel_centres(24, PIXEL_A)
SIGMA_A, AMPLITUDE = 0.6, 40.0  # a blurred atom; projected peak 60


def _images(position_A: np.ndarray) -> np.ndarray:
    """(V, 24, 24) projections of one Gaussian atom, float64."""
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float64)  # noqa: E731
    return project_gaussians(t(position_A[None]), t([SIGMA_A]), t([AMPLITUDE]), t(AXES), t(COORDS), t(COORDS)).numpy()


def test_curvature_matches_autograd_jacobian():
    """sum over views and pixels of (dI/dr)(dI/dr)^T, by autograd, equals the closed form to
    the accuracy of replacing the pixel sum by an integral (sigma = 2.4 px: below 1e-6)."""
    position = torch.tensor([[0.07, -0.11, 0.05]], dtype=torch.float64)
    args = [torch.as_tensor(a, dtype=torch.float64) for a in ([SIGMA_A], [AMPLITUDE], AXES, COORDS, COORDS)]
    jac = torch.func.jacfwd(lambda p: project_gaussians(p, *args))(position).reshape(-1, 3).numpy()
    noise = 2.0
    fisher = jac.T @ jac / noise**2
    std_l2 = position_std_A(np.array([SIGMA_A]), np.array([AMPLITUDE]), AXES, PIXEL_A, noise, loss="l2")[0]
    np.testing.assert_allclose(np.sqrt(np.diag(np.linalg.inv(fisher))), std_l2, rtol=1e-6)
    # The missing wedge: z (along the beam at 0 deg) is fixed less well than x; y (the tilt
    # axis, seen in every view) best.
    assert std_l2[1] < std_l2[0] < std_l2[2]


def _batch_images_and_jacobian(positions_A: np.ndarray):
    """(T, V*H*W) projections of one atom at each of T positions and their (T, V*H*W, 3)
    derivatives with respect to the position (closed form of the same 2D Gaussians)."""
    peak = AMPLITUDE * SIGMA_A * np.sqrt(2 * np.pi)
    u = np.einsum("vi,ti->tv", AXES[:, 0], positions_A)  # detector row coordinate per view
    v = np.einsum("vi,ti->tv", AXES[:, 1], positions_A)
    du = COORDS[None, None, :, None] - u[:, :, None, None]
    dv = COORDS[None, None, None, :] - v[:, :, None, None]
    image = peak * np.exp(-(du**2 + dv**2) / (2 * SIGMA_A**2))
    # dI/dr = I * (du * row_axis + dv * col_axis) / sigma^2
    jac = (image * du)[..., None] * AXES[None, :, None, None, 0, :] + (image * dv)[..., None] * AXES[
        None, :, None, None, 1, :
    ]
    t = positions_A.shape[0]
    return image.reshape(t, -1), jac.reshape(t, -1, 3) / SIGMA_A**2


@pytest.mark.parametrize("loss", ["l2", "l1"])
def test_predicted_precision_matches_repeated_fits(loss):
    """400 noisy copies of the same atom (peak-to-noise 15), each fitted by minimising the L2
    loss (Gauss-Newton) or the L1 loss (iteratively reweighted least squares, which converges
    to the L1 minimum): the scatter of the fitted positions matches the prediction per axis.
    With 400 fits a standard deviation is known to about 3.5% (1/sqrt(2*400)); allow 15%."""
    rng = np.random.default_rng(0)
    truth = np.array([0.03, -0.02, 0.04])
    noise, trials = 4.0, 400
    np.testing.assert_allclose(
        _batch_images_and_jacobian(truth[None])[0].reshape(_images(truth).shape), _images(truth), atol=1e-9
    )
    clean = _batch_images_and_jacobian(truth[None])[0]
    data = clean + rng.normal(0.0, noise, (trials, clean.shape[1]))
    fit = np.repeat(truth[None], trials, axis=0)
    # Least squares first (a few Gauss-Newton steps), then for L1 reweighting from there.
    for step in range(6 + (30 if loss == "l1" else 0)):
        image, jac = _batch_images_and_jacobian(fit)
        residual = data - image
        weight = 1.0 / np.maximum(np.abs(residual), 1e-3 * noise) if step >= 6 else np.ones_like(residual)
        weighted = jac * weight[..., None]
        normal = np.matmul(weighted.transpose(0, 2, 1), jac)
        fit = fit + np.linalg.solve(normal, np.matmul(weighted.transpose(0, 2, 1), residual[..., None]))[..., 0]
    scatter = np.std(fit - truth, axis=0)
    predicted = position_std_A(np.array([SIGMA_A]), np.array([AMPLITUDE]), AXES, PIXEL_A, noise, loss=loss)[0]
    np.testing.assert_allclose(scatter, predicted, rtol=0.15)


def test_noise_estimate_and_errors():
    rng = np.random.default_rng(1)
    residuals = rng.normal(0.0, 3.0, 100_000)
    residuals[:500] = 1e4  # a few pixels where the model is wrong barely move it
    assert robust_noise_std(residuals) == pytest.approx(3.0, rel=0.02)
    with pytest.raises(ValueError, match="three coordinates"):
        position_std_A(np.ones(1), np.ones(1), AXES[:1], PIXEL_A, 1.0)
    with pytest.raises(ValueError, match="loss"):
        position_std_A(np.ones(1), np.ones(1), AXES, PIXEL_A, 1.0, loss="huber")
