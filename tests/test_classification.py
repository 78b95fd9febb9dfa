"""Every Gaussian gets a class: species-like classes by mass and width, non-atoms by support."""

import numpy as np

from gaussian_atoms_method.atoms.classification import classify_gaussians, gaussian_mixture, gaussian_mixture_reference
from gaussian_atoms_method.atoms.pictures import write_population_png


def _two_element_particle(rng, n=600, bond_A=2.5):
    """A random packing of two elements (log mass 0 and 1.2, same width) inside a 12 Å sphere."""
    pos = []
    while len(pos) < n:
        p = rng.uniform(-12, 12, 3)
        if np.linalg.norm(p) < 12 and all(np.linalg.norm(p - q) > bond_A for q in pos[-200:]):
            pos.append(p)
    heavy = rng.random(n) < 0.4
    masses = np.exp(np.where(heavy, 1.2, 0.0) + 0.1 * rng.standard_normal(n))
    sigmas = 0.6 * np.exp(0.04 * rng.standard_normal(n))
    return np.array(pos), masses, sigmas, heavy


def test_two_populations_and_vacuum_blobs_are_told_apart(tmp_path):
    """Two elements 1.2 in log mass apart (12 spreads) come out as two classes, each atom in its
    own (99%), and 30 faint, wide blobs scattered in vacuum 5-9 Å outside the particle are
    non-atoms (no neighbour within twice the material's nearest distance) while every atom of
    the particle stays in the support."""
    rng = np.random.default_rng(0)
    pos, masses, sigmas, heavy = _two_element_particle(rng)
    direction = rng.normal(size=(30, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    vacuum = direction * rng.uniform(17, 21, (30, 1))
    all_pos = np.concatenate([pos, vacuum])
    all_masses = np.concatenate([masses, 0.2 * np.exp(rng.normal(0, 0.1, 30))])
    all_sigmas = np.concatenate([sigmas, 0.9 * np.ones(30)])
    result = classify_gaussians(all_masses, all_sigmas, all_pos)
    assert result.atoms[: len(pos)].all() and not result.atoms[len(pos) :].any()
    light, heavy_class = result.classes[: len(pos)][~heavy], result.classes[: len(pos)][heavy]
    assert np.mean(heavy_class == np.bincount(heavy_class).argmax()) > 0.99
    assert (
        np.mean(light == np.bincount(light).argmax()) > 0.99
        and np.bincount(light).argmax() < np.bincount(heavy_class).argmax()
    )
    counts = result.counts()
    assert counts["non-atoms"] == 30 and sum(v for k, v in counts.items() if k != "non-atoms") == len(pos)
    write_population_png(
        all_masses, all_sigmas, result.atoms, result.classes, len(result.class_means), None, tmp_path / "classes.png"
    )
    assert (tmp_path / "classes.png").stat().st_size > 10_000


def test_one_population_is_one_class():
    """One element, normally spread masses: the information criterion keeps one class."""
    rng = np.random.default_rng(1)
    pos, masses, sigmas, _ = _two_element_particle(rng)
    masses = np.exp(0.1 * rng.standard_normal(len(pos)))
    result = classify_gaussians(masses, sigmas, pos)
    assert len(result.class_means) == 1 and result.atoms.all()


def test_mixture_recovers_its_components():
    """EM on two well-separated 2D normals recovers their weights and means to sampling error."""
    rng = np.random.default_rng(2)
    x = np.concatenate([rng.normal([0, 0], 0.1, (700, 2)), rng.normal([1, 0.5], 0.1, (300, 2))])
    weights, means, _, _ = gaussian_mixture(x, 2)
    order = np.argsort(means[:, 0])
    np.testing.assert_allclose(weights[order], [0.7, 0.3], atol=0.01)
    np.testing.assert_allclose(means[order], [[0, 0], [1, 0.5]], atol=0.02)


def test_mixture_in_torch_follows_the_numpy_reference():
    """The torch EM (float64) takes the numpy reference's steps from the same seeds: weights,
    means and covariances agree to 1e-9 and the log-likelihood to 1e-12 of itself for one to
    four components (float64 sums in another order differ by about 1e-15 per step; EM contracts
    such differences)."""
    rng = np.random.default_rng(3)
    x = np.concatenate(
        [
            rng.normal([0, 0], [0.2, 0.1], (500, 2)),
            rng.normal([1, 0.3], [0.3, 0.1], (300, 2)),
            rng.normal([2, 0.1], [0.2, 0.05], (200, 2)),
        ]
    )
    for k in (1, 2, 3, 4):
        fast, slow = gaussian_mixture(x, k), gaussian_mixture_reference(x, k)
        for a, b in zip(fast[:3], slow[:3]):
            np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12)
        assert abs(fast[3] - slow[3]) <= 1e-12 * abs(slow[3])


def test_a_mixture_of_one_gaussian_is_finite_and_silent():
    """One Gaussian alone has no spread: its covariance is the ridge, finite, and torch is not
    asked for an unbiased covariance of one sample (0/0, a warning in the user's run)."""
    import warnings

    from gaussian_atoms_method.atoms.classification import gaussian_mixture

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        weights, means, covs, likelihood = gaussian_mixture(np.array([[1.0, 2.0]]), 1)
    np.testing.assert_allclose(weights, [1.0], rtol=1e-9)  # the mixture keeps each weight and mean 1e-12 off
    np.testing.assert_allclose(means, [[1.0, 2.0]], rtol=1e-9)
    assert np.all(np.isfinite(covs)) and np.isfinite(likelihood)
