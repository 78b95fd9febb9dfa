"""Peaks in a voxel volume (:mod:`gaussian_atoms_method.atoms.peaks`)."""

import numpy as np
from scipy import ndimage

from gaussian_atoms_method.atoms.maxima import local_maxima_host
from gaussian_atoms_method.atoms.peaks import parabola_vertex


def test_local_maxima_above_a_level_equal_the_maximum_filter():
    """The sparse search (only voxels above the level compared with their neighbours) and the
    maximum filter give the same maxima, ties included, at any level."""
    rng = np.random.default_rng(1)
    volume = ndimage.gaussian_filter(rng.standard_normal((30, 40, 20)), 1.2).astype(np.float32)
    volume[5, 5, 5] = volume[5, 5, 6] = volume.max() + 1
    full = (volume == ndimage.maximum_filter(volume, size=3, mode="nearest")) & (volume > 0)
    full[[0, -1]] = full[:, [0, -1]] = full[:, :, [0, -1]] = False
    every = np.argwhere(full)
    for level in (-np.inf, 0.0, 0.1, 0.3):
        np.testing.assert_array_equal(local_maxima_host(volume, level), every[volume[tuple(every.T)] > level])


def test_parabola_vertex_is_exact_and_clipped():
    """Three samples of -(x - 0.3)^2 at -1, 0, 1 put the vertex at 0.3; a vertex beyond half a
    voxel is clipped to it; a convex or flat triple gives 0."""
    x = np.array([-1.0, 0.0, 1.0])
    below, centre, above = -((x - 0.3) ** 2)
    np.testing.assert_allclose(
        parabola_vertex(np.array([below]), np.array([centre]), np.array([above])), [0.3], atol=1e-12
    )
    below, centre, above = -((x - 2.0) ** 2)
    assert parabola_vertex(np.array([below]), np.array([centre]), np.array([above]))[0] == 0.5
    assert parabola_vertex(np.array([1.0, 1.0]), np.array([0.0, 1.0]), np.array([1.0, 1.0])).tolist() == [0.0, 0.0]
