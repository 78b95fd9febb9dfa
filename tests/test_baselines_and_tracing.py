"""Voxel baselines (FBP, SART) and atom tracing."""

import numpy as np
import pytest
import torch

from gaussian_atoms_method.atoms.matching import score_atoms
from gaussian_atoms_method.atoms.maxima import suppress_within_host
from gaussian_atoms_method.harness.simulate import parse_tilts, simulate_tilt_series, spherical_particle
from gaussian_atoms_method.harness.tracing import trace_atoms
from gaussian_atoms_method.physics.reconstruction import reconstruct


def _blobs(centres_vox, shape=(40, 40, 40), sigma=2.4, amps=None):
    idx = np.stack(np.meshgrid(*[np.arange(s) for s in shape], indexing="ij"), -1)
    vol = np.zeros(shape)
    amps = np.ones(len(centres_vox)) if amps is None else amps
    for c, a in zip(centres_vox, amps):
        vol += a * np.exp(-((idx - c) ** 2).sum(-1) / (2 * sigma**2))
    return vol


def test_trace_finds_subvoxel_peaks():
    """Gaussian peaks at sub-voxel positions: the parabola refinement gets them to a few pm."""
    rng = np.random.default_rng(0)
    centres = np.array([[10.3, 12.7, 20.1], [25.6, 14.2, 9.9], [20.0, 30.45, 28.8], [30.2, 30.3, 15.5]])
    vol = _blobs(centres) + rng.normal(0, 0.002, (40, 40, 40))
    idx, values = trace_atoms(vol, spacing_A=0.25)
    assert len(idx) == 4
    order = np.argsort(idx[:, 0])
    err_A = np.linalg.norm(idx[order] - centres[np.argsort(centres[:, 0])], axis=1) * 0.25
    # The log-parabola is exact for a Gaussian; 0.2% noise moves it by about 0.01 voxel.
    assert err_A.max() < 0.0125  # 1.25 pm


def test_minimum_distance_keeps_the_brighter():
    # 1.5 Å apart
    vol = _blobs(np.array([[20.0, 20.0, 20.0], [26.0, 20.0, 20.0]]), sigma=1.5, amps=np.array([1.0, 0.8]))
    idx, _ = trace_atoms(vol, spacing_A=0.25, min_distance_A=2.0, threshold=0.1)
    assert len(idx) == 1 and abs(idx[0, 0] - 20.0) < 0.3
    idx, _ = trace_atoms(vol, spacing_A=0.25, min_distance_A=1.0, threshold=0.1)
    assert len(idx) == 2


def test_suppress_within_order_and_inclusive_radius():
    pos = np.array([[0.0, 0, 0], [2.0, 0, 0], [4.0, 0, 0]])
    # Visiting the middle first suppresses both ends (exactly 2.0 away counts as within).
    assert suppress_within_host(pos, np.array([1, 0, 2]), 2.0).tolist() == [1]
    assert suppress_within_host(pos, np.array([0, 1, 2]), 2.0).tolist() == [0, 2]


def test_otsu_threshold_rejects_noise_maxima():
    """27 atoms among ~thousands of noise maxima (5% of the peak): Otsu keeps exactly the atoms."""
    rng = np.random.default_rng(1)
    g = np.array([8.0, 20.0, 32.0])
    centres = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    vol = _blobs(centres) + rng.normal(0, 0.05, (40, 40, 40))
    idx, _ = trace_atoms(vol, spacing_A=0.25)
    assert len(idx) == 27


@pytest.mark.parametrize("pixels, tilt_axis", [(64, "y"), (65, "y"), (64, "x")])
def test_baselines_recover_atoms_with_our_convention(pixels, tilt_axis):
    """FBP and SART + tracing on a full tilt range of clean Gaussian data find every atom where
    our convention says it is (even and odd detectors, both tilt axes)."""
    atoms = spherical_particle("Au", 6.0)
    sim = simulate_tilt_series(
        atoms, parse_tilts("-90:2:88"), potential="gaussian", detector_pixels=pixels, noise_std=2.0, tilt_axis=tilt_axis
    )
    for method, rmsd_pm in (("fbp", 3.0), ("sart", 15.0)):
        vol = reconstruct(sim.projections, sim.angles_deg, sim.pixel_size_A, method, tilt_axis, sart_iterations=1)
        idx, _ = trace_atoms(vol.data, vol.spacing_A)
        s = score_atoms(vol.index_to_A(idx), atoms.positions)
        # Every atom found; a handful of false maxima at most; FBP positions to a few pm (a
        # half-pixel convention error would cost ~12 pm), one SART sweep is not converged.
        assert s["tpr"] == 1.0 and s["fp_per_true_atom"] <= 0.15, (method, s)
        assert s["rmsd_pm"] < rmsd_pm, (method, s)


def test_reconstruct_rejects_unknown_method():
    with pytest.raises(ValueError, match="method"):
        reconstruct(np.zeros((2, 5, 5)), [0.0, 10.0], 0.25, "art")


def test_batched_filtered_backprojection_equals_scikit_image():
    """The sparse-matrix FBP is scikit-image's iradon slice by slice, to float64 rounding, for
    both filters the package uses, for output slices smaller and larger than the detector, and
    when the matrix is built in blocks of a few output rows."""
    from skimage.transform import iradon

    from gaussian_atoms_method.physics.reconstruction import filtered_backprojection

    rng = np.random.default_rng(0)
    sino = rng.normal(size=(3, 41, 17))
    theta = np.linspace(-70, 68, 17)
    for name in ("ramp", "hann"):
        expected = np.stack([iradon(s, theta=theta, filter_name=name, circle=False, output_size=41) for s in sino])
        np.testing.assert_allclose(filtered_backprojection(sino, theta, name, 41), expected, rtol=0, atol=1e-12)
    for size in (29, 57):
        expected = np.stack([iradon(s, theta=theta, output_size=size, circle=False) for s in sino])
        np.testing.assert_allclose(filtered_backprojection(sino, theta, output_size=size), expected, rtol=0, atol=1e-12)
        blocks = filtered_backprojection(sino, theta, output_size=size, max_matrix_entries=7 * 2 * len(theta))
        np.testing.assert_allclose(blocks, expected, rtol=0, atol=1e-12)
    # float32, kept as a tensor (the start's): iradon's values to float32 rounding (1e-6 of the largest)
    single = filtered_backprojection(sino, theta, output_size=57, dtype=torch.float32, as_tensor=True)
    assert isinstance(single, torch.Tensor) and single.dtype == torch.float32
    np.testing.assert_allclose(single.numpy(), expected, rtol=0, atol=1e-6 * np.abs(expected).max())
    with pytest.raises(ValueError, match="angles"):
        filtered_backprojection(sino, theta[:-1])


def test_the_fourier_filters_are_scikit_images():
    """Every filter iradon offers, computed without importing skimage.transform: its values to
    the bit, at a power-of-two size and the smallest one the FBP uses (64)."""
    from skimage.transform.radon_transform import _get_fourier_filter

    from gaussian_atoms_method.physics.fbp_filters import fourier_filter_of

    for size in (64, 512):
        for name in ("ramp", "shepp-logan", "cosine", "hamming", "hann", None):
            np.testing.assert_array_equal(fourier_filter_of(size, name), _get_fourier_filter(size, name)[:, 0])
    with pytest.raises(ValueError, match="filter_name"):
        fourier_filter_of(64, "parzen")


def test_the_filter_as_a_matrix_is_the_ffts_filter():
    """A GPU's FBP filters by one matrix product (no cuFFT); the matrix gives the host's FFT
    filtering (zero-padded to ``padded``, the first L samples kept) to float64 rounding, for an
    odd and an even detector and both filters the package uses."""
    import scipy.fft

    from gaussian_atoms_method.physics.fbp_filters import even_filter, filter_matrix

    rng = np.random.default_rng(2)
    for length, name in ((41, "ramp"), (64, "hann")):
        padded, even = even_filter(length, name)
        projections = rng.normal(size=(5, length))
        expected = scipy.fft.irfft(scipy.fft.rfft(projections, n=padded) * even, n=padded)[:, :length] * (np.pi / 34)
        matrix = filter_matrix(even, padded, length, 17)
        np.testing.assert_allclose(matrix, matrix.T, rtol=0, atol=1e-15 * np.abs(matrix).max())
        np.testing.assert_allclose(projections @ matrix, expected, rtol=0, atol=1e-13 * np.abs(expected).max())


def test_the_hosts_backprojection_matrix_is_torchs():
    """The CPU's FBP builds its sparse matrix in numpy for scipy (without torch): the same
    entries as the torch builder the GPU and SIRT use, to the bit, whole and in blocks of rows."""
    from gaussian_atoms_method.physics.reconstruction import backprojection_matrix, backprojection_matrix_on_host

    theta = np.linspace(-70, 68, 17)
    for size, rows in ((41, None), (29, slice(100, 357)), (57, slice(0, 5))):
        on_host = backprojection_matrix_on_host(theta, 41, size, rows, np.float32)
        in_torch = backprojection_matrix(theta, 41, size, rows, torch.float32)
        assert on_host.dtype == np.float32 and on_host.shape == tuple(in_torch.shape)
        np.testing.assert_array_equal(on_host.toarray(), in_torch.to_dense().numpy())


def test_the_back_projection_summed_angle_by_angle_is_the_matrix_product():
    """Off the CPU the FBP gathers each angle's two detector samples and adds them in one fixed
    order (cuSPARSE's product of the same matrix is not repeatable): the matrix product to
    float64 rounding, whole and in blocks of output rows, with the missed rays reading zero."""
    from gaussian_atoms_method.physics.reconstruction import backproject_in_order, backprojection_matrix

    rng = np.random.default_rng(3)
    theta = np.linspace(-70, 68, 17)
    for length, size, rows in ((41, 41, slice(0, 41 * 41)), (41, 57, slice(100, 2000)), (40, 29, slice(0, 5))):
        filtered = torch.as_tensor(rng.normal(size=(len(theta) * (length + 1), 3)))
        filtered[length :: length + 1] = 0.0  # each angle's zero sample
        expected = backprojection_matrix(theta, length, size, rows) @ filtered
        out = torch.empty_like(expected)
        backproject_in_order(filtered, theta, length, size, rows, out)
        np.testing.assert_allclose(out.numpy(), expected.numpy(), rtol=0, atol=1e-13 * float(expected.abs().max()))


@pytest.mark.parametrize("shift_px", [0.5, -3.3])
def test_sinograms_shifted_by_one_matrix_equal_scipys_shift_of_the_stack(shift_px):
    """An even detector's sinograms move half a pixel to centre the tilt axis: one product with
    :func:`shift_matrix` along the detector axis, the same as scipy's cubic-spline shift of the
    whole (S, L, N) stack (which interpolates the unshifted axes at their samples, so exactly)
    to float64 rounding."""
    import scipy.ndimage

    from gaussian_atoms_method.physics.reconstruction import shift_matrix

    stack = np.random.default_rng(0).standard_normal((6, 21, 5))
    expected = scipy.ndimage.shift(stack, (0, shift_px, 0), order=3, mode="constant")
    np.testing.assert_allclose(np.matmul(shift_matrix(21, shift_px), stack), expected, rtol=0, atol=1e-12)


def test_torchs_sparse_notes_are_hidden_for_our_matrices_only():
    """torch says once per process that sparse CSR is in beta and that invariant checks are off;
    for the matrices the physics builds valid by construction the note is hidden, for the same
    words raised from a user's own code it is not."""
    import warnings

    from gaussian_atoms_method.physics import quiet_sparse_notes

    words = "Sparse invariant checks are implicitly disabled. Memory errors (e.g. SEGFAULT) will occur"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        quiet_sparse_notes()  # as at import, in front of the test's own filter
        for module in ("gaussian_atoms_method.physics.reconstruction", "gaussian_atoms_method.launch.kernel_warmup"):
            warnings.warn_explicit(words, UserWarning, "ours.py", 1, module=module)
        warnings.warn_explicit("Sparse CSR tensor support is in beta state", UserWarning, "ours.py", 2, module=module)
        warnings.warn_explicit(words, UserWarning, "mine.py", 1, module="my_analysis")
    assert [w.filename for w in caught] == ["mine.py"]
