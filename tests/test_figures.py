"""Slices of the reconstructed potential with atoms overlaid."""

import numpy as np
import pytest
from PIL import Image

from gaussian_atoms_method.atoms.atom_set import AtomSet
from gaussian_atoms_method.atoms.slices import potential_on_plane, write_slices_png
from gaussian_atoms_method.harness.metrics import voxelise_gaussians


def _atoms(n=40, seed=0):
    rng = np.random.default_rng(seed)
    return AtomSet(rng.uniform(-6, 6, (n, 3)), sigmas=rng.uniform(0.4, 0.8, n), amplitudes=rng.uniform(1, 3, n))


def test_plane_equals_the_central_slice_of_the_voxelised_potential():
    """The separable plane evaluation and the voxel grid sample the same sum of Gaussians
    (voxelise_gaussians cuts each Gaussian at 4 sigma, as the plane does: exp(-8) = 3e-4 of a
    peak is the most they can differ by)."""
    atoms = _atoms()
    n, spacing = 61, 0.25
    volume = voxelise_gaussians(atoms.positions, atoms.sigmas, atoms.amplitudes, spacing, (n, n, n))
    coords = (np.arange(n) - (n - 1) / 2) * spacing
    for normal, u, v, sl in ((2, 0, 1, volume[:, :, n // 2]), (1, 0, 2, volume[:, n // 2, :]), (0, 1, 2, volume[n // 2])):
        plane = potential_on_plane(atoms, normal, 0.0, u, v, coords, coords)
        np.testing.assert_allclose(plane, sl, atol=3.5e-4 * atoms.amplitudes.max() * 4)


def test_slices_png_is_written_complete(tmp_path):
    pred, truth = _atoms(), _atoms()
    path = write_slices_png(pred, tmp_path / "slices.png", truth, title="test")
    image = Image.open(path)
    assert image.format == "PNG" and image.size[0] > image.size[1] > 300
    assert not list(tmp_path.glob(".slices*"))  # no temporary file left
    with pytest.raises(ValueError, match="sigma_A"):
        write_slices_png(AtomSet(np.zeros((2, 3))), tmp_path / "x.png")
