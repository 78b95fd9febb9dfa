"""The projector against independent computations of the same line integrals."""

import math

import numpy as np
import pytest
import torch
from scipy import integrate

from gaussian_atoms_method.physics.geometry import detector_axes_from_tilts, pixel_centres, project_volume
from gaussian_atoms_method.physics.projector import gaussian_mass, project_gaussians


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
            val, _ = integrate.quad(
                lambda t: density(origin + t * axes[v, 2]), -15, 15, epsabs=1e-13, epsrel=1e-12, limit=200
            )
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
    assert torch.autograd.gradcheck(
        lambda m, s, a: project_gaussians(m, s, a, axes, coords, coords), (means, sigmas, amps)
    )


def test_shape_errors():
    axes = torch.tensor(detector_axes_from_tilts([0.0]))
    c = torch.zeros(4, dtype=torch.float64)
    with pytest.raises(ValueError, match="means"):
        project_gaussians(torch.zeros(3, 2, dtype=torch.float64), torch.ones(3), torch.ones(3), axes, c, c)
    with pytest.raises(ValueError, match="sigmas"):
        project_gaussians(torch.zeros(3, 3, dtype=torch.float64), torch.ones(2), torch.ones(3), axes, c, c)


def _random_scene(n, seed, sigma_px_range=(0.5, 4.0), spread=0.6, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) * spread
    lo, hi = sigma_px_range
    sigmas = (lo + (hi - lo) * torch.rand(n, generator=g, dtype=dtype)) / 100.0  # pixels of 1/100
    amps = 10 ** (torch.rand(n, generator=g, dtype=dtype) * 3 - 1)
    return means, sigmas, amps


@pytest.mark.parametrize(
    "n, sigma_px_range, spread, tile",
    [
        (500, (0.5, 4.0), 0.6, 32),  # atoms inside the detector
        (300, (0.5, 4.0), 1.4, 16),  # many centres beyond the detector edge
        (40, (15.0, 20.0), 0.6, 32),  # windows much wider than a tile
        (40, (0.05, 0.2), 0.6, 8),  # needles narrower than a pixel
    ],
)
def test_tiled_matches_dense(n, sigma_px_range, spread, tile):
    """The tiled projector reproduces the exact dense one (values and gradients, float64):
    the only difference is the tails cut at 5.5 sigma, exp(-5.5^2 / 2) = 2.7e-7 of a peak."""
    from gaussian_atoms_method.physics.projector import project_gaussians_tiled

    means, sigmas, amps = _random_scene(n, seed=n, sigma_px_range=sigma_px_range, spread=spread)
    axes = torch.tensor(detector_axes_from_tilts(np.array([-70.0, -12.0, 33.0, 90.0]), "y"), dtype=torch.float64)
    rows = (torch.arange(100, dtype=torch.float64) + 0.5 - 50) / 100
    cols = (torch.arange(90, dtype=torch.float64) + 0.5 - 47) / 100  # not square, off-centre
    weights = torch.rand(4, 100, 90, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    results = []
    for project in (project_gaussians, lambda *a: project_gaussians_tiled(*a, tile=tile)):
        params = [p.clone().requires_grad_() for p in (means, sigmas, amps)]
        img = project(*params, axes, rows, cols)
        (img * weights).sum().backward()
        results.append((img.detach(), [p.grad for p in params]))
    (dense, dense_grads), (tiled, tiled_grads) = results
    peak_scale = float((amps * sigmas * math.sqrt(2 * math.pi)).max())
    assert float((dense - tiled).abs().max()) <= 1e-6 * peak_scale
    for gd, gt in zip(dense_grads, tiled_grads):
        assert float((gd - gt).abs().max()) <= 1e-5 * float(gd.abs().max())


def test_tiled_float32_agrees_with_float64():
    """In float32 the tiled projector is as accurate as the arithmetic allows (1e-5 of the image peak)."""
    from gaussian_atoms_method.physics.projector import project_gaussians_tiled

    means, sigmas, amps = _random_scene(2000, seed=7)
    axes = torch.tensor(detector_axes_from_tilts(np.array([5.0, 61.0]), "x"), dtype=torch.float64)
    coords = (torch.arange(128, dtype=torch.float64) + 0.5 - 64) / 100
    exact = project_gaussians(means, sigmas, amps, axes, coords, coords)
    single = project_gaussians_tiled(*(t.float() for t in (means, sigmas, amps, axes, coords, coords)))
    assert float((single.double() - exact).abs().max()) <= 1e-5 * float(exact.abs().max())


def test_tile_blocks_backward_matches_autograd():
    """The tiles' hand-written backward gives autograd's gradients of the plain product
    (float64; gradcheck against finite differences too), with padded slots (peak 0, factor -1)
    and terms deep below float32's range (17 widths away) among the tiles' Gaussians; the
    exponent's floor moves a value by at most exp(-87) per term."""
    from gaussian_atoms_method.physics.tiles import tile_blocks, tile_blocks_reference

    gen = torch.Generator().manual_seed(5)
    n_tiles, tile, k = 6, 8, 5
    pixels = (
        torch.arange(tile, dtype=torch.float64)[None, :] + 8.0 * torch.arange(n_tiles, dtype=torch.float64)[:, None]
    )
    U = (pixels[:, :1] + torch.rand(n_tiles, k, generator=gen, dtype=torch.float64) * 40 - 16).requires_grad_()
    V = (pixels[:, :1] + torch.rand(n_tiles, k, generator=gen, dtype=torch.float64) * 40 - 16).requires_grad_()
    P = (torch.rand(n_tiles, k, generator=gen, dtype=torch.float64) + 0.1).detach()
    S = (-0.5 / (torch.rand(n_tiles, k, generator=gen, dtype=torch.float64) * 3 + 0.3) ** 2).detach()
    P[:, -1], S[:, -1] = 0.0, -1.0  # a padded slot, as the tiled projector fills them
    P.requires_grad_(), S.requires_grad_()
    rows, cols = (pixels + 0.3).requires_grad_(), (pixels - 0.2).requires_grad_()  # a view's shift moves the pixels
    inputs = (U, V, P, S, rows, cols)
    weights = torch.randn(n_tiles, tile, tile, generator=gen, dtype=torch.float64)
    fast, plain = tile_blocks(*inputs), tile_blocks_reference(*inputs)
    assert float((fast - plain).detach().abs().max()) <= k * math.exp(-87.0)
    for got, want in zip(
        torch.autograd.grad((fast * weights).sum(), inputs), torch.autograd.grad((plain * weights).sum(), inputs)
    ):
        assert float((got - want).abs().max()) <= 1e-12 * max(float(want.abs().max()), 1.0)
    assert torch.autograd.gradcheck(tile_blocks, inputs)
    # fixed pixels: no gradient asked for them
    assert torch.autograd.gradcheck(lambda *a: tile_blocks(*a, pixels, pixels), inputs[:4])


def test_tile_order_is_torchs_stable_order():
    """The tiles' sort (numpy's radix sort of 16-bit indices on the CPU) lists the pairs in
    torch's stable order, with many ties, and past 16 bits too (torch's own sort there)."""
    from gaussian_atoms_method.physics.tiles import tile_order

    gen = torch.Generator().manual_seed(2)
    for n_tiles in (81, 40_000):
        tile_id = torch.randint(0, n_tiles, (5000,), generator=gen)
        assert torch.equal(tile_order(tile_id, n_tiles), torch.argsort(tile_id, stable=True))


def test_tiled_empty_and_invisible():
    """No Gaussians, or none reaching the detector, give an all-zero image of the right shape."""
    from gaussian_atoms_method.physics.projector import project_gaussians_tiled

    axes = torch.tensor(detector_axes_from_tilts(np.array([0.0]), "y"), dtype=torch.float64)
    coords = (torch.arange(20, dtype=torch.float64) - 9.5) / 20
    empty = project_gaussians_tiled(
        torch.zeros(0, 3, dtype=torch.float64),
        torch.zeros(0, dtype=torch.float64),
        torch.zeros(0, dtype=torch.float64),
        axes,
        coords,
        coords,
    )
    assert empty.shape == (1, 20, 20) and float(empty.abs().max()) == 0.0
    far = torch.tensor([[5.0, 5.0, 0.0]], dtype=torch.float64)
    img = project_gaussians_tiled(
        far, torch.tensor([0.01], dtype=torch.float64), torch.tensor([1.0], dtype=torch.float64), axes, coords, coords
    )
    assert float(img.abs().max()) == 0.0
    with pytest.raises(ValueError, match="evenly spaced"):
        project_gaussians_tiled(
            far,
            torch.tensor([0.01], dtype=torch.float64),
            torch.tensor([1.0], dtype=torch.float64),
            axes,
            coords**3,
            coords,
        )


def test_anisotropic_matches_quadrature_and_isotropic():
    """General Gaussians: pixels equal the integral along the beam (quadrature), and with
    C = sigma^2 I the anisotropic projector reproduces the isotropic one."""
    from gaussian_atoms_method.physics.projector import covariances_from_scales_quats, project_anisotropic_gaussians

    rng = np.random.default_rng(4)
    means = torch.tensor(rng.uniform(-1.5, 1.5, size=(3, 3)))
    log_scales = torch.log(torch.tensor([[0.3, 0.5, 0.9], [0.6, 0.6, 0.6], [0.25, 0.8, 0.4]], dtype=torch.float64))
    quats = torch.tensor(rng.normal(size=(3, 4)))
    cov = covariances_from_scales_quats(log_scales, quats)
    amps = torch.tensor([1.0, 0.5, 2.0], dtype=torch.float64)
    angles = np.array([-55.0, 0.0, 38.0])
    n, px = 40, 0.15
    coords = torch.tensor(pixel_centres(n, px))
    axes = torch.tensor(detector_axes_from_tilts(angles, "y"))
    img = project_anisotropic_gaussians(means, cov, amps, axes, coords, coords).numpy()
    inv = np.linalg.inv(cov.numpy())

    def density(r):
        d = r[None, :] - means.numpy()
        return float((amps.numpy() * np.exp(-0.5 * np.einsum("ni,nij,nj->n", d, inv, d))).sum())

    worst = 0.0
    for v in range(len(angles)):
        for i, j in [(20, 20), (12, 25), (27, 9), (15, 15)]:
            origin = coords[i].item() * axes[v, 0].numpy() + coords[j].item() * axes[v, 1].numpy()
            val, _ = integrate.quad(
                lambda t: density(origin + t * axes[v, 2].numpy()), -12, 12, epsabs=1e-13, epsrel=1e-12, limit=200
            )
            worst = max(worst, abs(img[v, i, j] - val) / float(img[v].max()))
    assert worst < 1e-6  # the window cut-off (2.7e-7 of a peak) is the only approximation

    sig = torch.tensor([0.4, 0.7, 0.55], dtype=torch.float64)
    iso = project_gaussians(means, sig, amps, axes, coords, coords)
    aniso = project_anisotropic_gaussians(
        means, torch.diag_embed(sig[:, None].expand(3, 3) ** 2), amps, axes, coords, coords
    )
    assert float((iso - aniso).abs().max()) <= 1e-6 * float(iso.max())


def test_typical_mass_is_the_mass_weighted_median():
    """Half of the total mass sits in entries at least as heavy as the typical mass: 100 atoms
    of mass 1 stay typical beside 1,000 faint leftovers of 0.001 (a plain median would be
    0.001), and one heavy entry carrying most of the mass becomes the typical one."""
    from gaussian_atoms_method.physics.projector import typical_mass

    atoms_and_faint = torch.cat([torch.ones(100), torch.full((1000,), 1e-3)])
    assert typical_mass(atoms_and_faint) == 1.0
    assert typical_mass(torch.tensor([1.0, 1.0, 10.0])) == 10.0
    assert typical_mass(torch.zeros(0)) == 0.0


def test_the_tiled_projectors_gather_has_the_same_gradient_every_time_on_a_cpu():
    """Each Gaussian's gradient sums its share of every tile it touches.  Summed from two threads at
    once (an indexing's ``index_put_`` accumulating) the float32 sum's order, so its rounding,
    changed from run to run; ``pad_gather`` sums in one order.  A 54,000-atom fit's tile lists
    hold millions of (Gaussian, tile) slots: 2,000 tiles of 1,000 slots over 4,000 Gaussians here,
    five backward passes, bit for bit equal."""
    from gaussian_atoms_method.physics.tiles import pad_gather

    gen = torch.Generator().manual_seed(0)
    values = torch.randn(2, 2000, generator=gen).requires_grad_()
    index = torch.randint(0, 4001, (2000, 1000), generator=gen)  # 4,000 Gaussians and the sentinel
    weights = torch.randn(2000, 1000, generator=gen)
    grads, threads = [], torch.get_num_threads()
    torch.set_num_threads(2)  # the suite runs one thread a worker; the race needs two
    try:
        for _ in range(5):
            values.grad = None
            (pad_gather(values, index) * weights).sum().backward()
            grads.append(values.grad.clone())
    finally:
        torch.set_num_threads(threads)
    assert all(torch.equal(grads[0], g) for g in grads[1:])
    expected = torch.cat([values.detach().reshape(-1), torch.zeros(1)])[index]
    assert torch.equal(pad_gather(values, index).detach(), expected)
