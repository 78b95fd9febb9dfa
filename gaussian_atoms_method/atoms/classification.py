"""Atoms and non-atoms: every fitted Gaussian gets a class from its population and its place.

The classical pipeline classifies every traced peak (k-means into species and "non-atom").  Here:

* **classes** from the population: a Gaussian mixture on (log mass, log width) with as many
  components as the Bayesian information criterion picks (1 to :data:`MAX_CLASSES`), each
  Gaussian in its most probable component, components numbered by increasing mean mass (heavier
  elements scatter more: class 1 is the lightest).  A description of the population, not yet
  species: one element whose masses are not normally distributed (a probe's tails widen some
  atoms) also takes several components; ``gaussian-atoms export --species`` names elements;
* **non-atom classes** by population: the class holding the most mass among the supported
  Gaussians is the confident atoms; a class most of whose members have no confident atom within
  the far-out fence of the confident atoms' own nearest-neighbour distances lies outside their
  support (a probe's or a denoiser's leftovers in the vacuum around a carbon particle: wider and
  lighter, more than 2 Å from any atom) and is reported as non-atoms, whole
  (:func:`population_support`);
* **support** from the atoms themselves: a Gaussian with fewer than two neighbours within the
  larger of the far-out fence of the nearest-neighbour distances (upper quartile plus three
  interquartile ranges; Tukey's) and twice their median stands apart from the material, in
  vacuum, and is a non-atom whatever its class.  A real atom has a neighbour a bond away and
  others in the second shell, within twice the bond (C 2.46/1.42, a-Si 3.8/2.35, fcc 4.08/2.88
  Å), even at a surface; noise blobs and a probe's or a floor's leftovers in vacuum have none,
  or one another.  The fence alone is too tight for a narrow bond distribution: on a
  simulated carbon particle it cut five real atoms 1.7-1.8 Å from their nearest found neighbour.

numpy, and torch for the mixture (:func:`gaussian_mixture`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from gaussian_atoms_method.atoms.pair_distribution import nearest_neighbour_distances

MIXTURE_STARTS = 4
"""The mixture of each number of classes is fitted from this many k-means++ starts and the most
likely kept, so that the information criterion compares each number's best fit, not the one its
start fell into.  From one start, two fits of each of the Ta film's sub-areas 23, 25 and 21 that
differ only at the rounding level picked three classes in one and two or four in the other (the
three's log-likelihood 17-25 below its best there); sub-area 23 dropped a light class in one and
kept it in the other: 0.137 against 0.276 extra atoms per model atom
(``docs/studies/overlap_disagreement.md``).  With four starts all six picked three, as with eight."""
MAX_CLASSES = 4
"""At most this many classes: species told apart by mass (the benchmarks hold up to three
elements) and one more for a population that is not atoms."""
FENCE_IQR = 3.0
"""Tukey's far-out fence: beyond the upper quartile by three interquartile ranges a distance is
an outlier of the material's own nearest-neighbour distances."""


@dataclass
class Classification:
    """Per Gaussian: its class (1..k, by increasing mean mass) and whether it is in the support."""

    classes: np.ndarray
    in_support: np.ndarray
    class_means: np.ndarray
    """(k, 2) each class's mean (log mass, log width)."""
    bic: dict

    @property
    def atoms(self) -> np.ndarray:
        """(N,) bool: reported as atoms (in the support)."""
        return self.in_support

    def counts(self) -> dict[str, int]:
        """Atoms per class and the non-atoms."""
        out = {
            f"class {k + 1}": int(np.sum(self.atoms & (self.classes == k + 1))) for k in range(len(self.class_means))
        }
        out["non-atoms"] = int(np.sum(~self.atoms))
        return out


def _seeds(x: np.ndarray, k: int, seed: int) -> np.ndarray:
    """(k, D) k-means++ seeds of (N, D) ``x``."""
    n = len(x)
    rng = np.random.default_rng(seed)
    centres = [x[rng.integers(n)]]
    for _ in range(1, k):
        d2 = np.min([((x - c) ** 2).sum(axis=1) for c in centres], axis=0)
        centres.append(x[rng.choice(n, p=d2 / d2.sum())] if d2.sum() > 0 else x[rng.integers(n)])
    return np.array(centres)


def gaussian_mixture(
    x: np.ndarray, k: int, iterations: int = 200, seed: int = 0, device: str | torch.device = "cpu"
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """EM for a ``k``-component Gaussian mixture with full covariances on (N, D) ``x``, in
    float64 torch on ``device``.

    Starts from k-means++ seeds; covariances are regularised by 1e-6 of the data's variance;
    stops when an iteration raises the log-likelihood by less than 1e-8 of it.  Returns the
    weights (k,), means (k, D), covariances (k, D, D) and the log-likelihood.  The same
    iterations as :func:`gaussian_mixture_reference` (numpy); torch because numpy's ``exp`` and
    reductions over four components were the final stage's largest cost at many atoms after the
    pair distribution."""
    n, d = x.shape
    X = torch.as_tensor(np.asarray(x, dtype=np.float64), device=device)
    Xt = X.T.contiguous()  # (D, N): N the long, contiguous axis of every product (4-10x faster on a CPU)
    means = torch.as_tensor(_seeds(np.asarray(x, dtype=np.float64), k, seed), device=device)
    ridge = 1e-6 * torch.diag(torch.atleast_1d(X.var(dim=0, unbiased=False) + 1e-12))
    # one Gaussian alone has no spread: its covariance is the ridge (unbiased, it would be 0/0)
    covs = (torch.cov(Xt, correction=1 if n > 1 else 0).reshape(d, d) + ridge).expand(k, d, d).clone()
    weights = torch.full((k,), 1.0 / k, dtype=torch.float64, device=device)
    previous = -math.inf
    for _ in range(iterations):
        log_p = _log_normals(Xt, means, covs) + weights.log()[:, None]
        log_total = torch.logsumexp(log_p, dim=0)
        resp = torch.exp(log_p - log_total)
        likelihood = float(log_total.sum())
        nk = resp.sum(dim=1) + 1e-12
        weights = nk / n
        means = (resp @ X) / nk[:, None]
        diff = Xt[None] - means[:, :, None]
        covs = (resp[:, None, :] * diff) @ diff.transpose(1, 2) / nk[:, None, None] + ridge
        if likelihood - previous < 1e-8 * abs(likelihood):
            break
        previous = likelihood
    return weights.cpu().numpy(), means.cpu().numpy(), covs.cpu().numpy(), likelihood


def _log_normals(Xt: torch.Tensor, means: torch.Tensor, covs: torch.Tensor) -> torch.Tensor:
    """(k, N) the log density of each of k normals (means (k, D), covariances (k, D, D)) at the
    N points of (D, N) ``Xt``."""
    diff = Xt[None] - means[:, :, None]
    inverse, logdet = _inverse_and_logdet(covs)
    maha = ((inverse @ diff) * diff).sum(dim=1)
    return -0.5 * (maha + logdet[:, None] + Xt.shape[0] * math.log(2 * math.pi))


def _inverse_and_logdet(covs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The inverses and log-determinants of k (D, D) covariances on their device.  For D of 1
    or 2 (a mass and a width) in closed form there; otherwise on the host: a GPU's solver is slow
    for such small matrices, and the host's copies back would each wait for the GPU."""
    d = covs.shape[-1]
    if d == 1:
        return 1.0 / covs, torch.log(covs[:, 0, 0])
    if d == 2:
        a, b, c, e = covs[:, 0, 0], covs[:, 0, 1], covs[:, 1, 0], covs[:, 1, 1]
        det = a * e - b * c
        inverse = torch.stack([torch.stack([e, -b], dim=-1), torch.stack([-c, a], dim=-1)], dim=-2) / det[:, None, None]
        return inverse, torch.log(det)
    small = covs.cpu()
    return torch.linalg.inv(small).to(covs.device), torch.linalg.slogdet(small)[1].to(covs.device)


def gaussian_mixture_reference(
    x: np.ndarray, k: int, iterations: int = 200, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """:func:`gaussian_mixture` in numpy, one component at a time (the tests' reference)."""
    n, d = x.shape
    means = _seeds(x, k, seed)
    ridge = 1e-6 * np.diag(np.atleast_1d(x.var(axis=0) + 1e-12))
    covs = np.array([np.cov(x.T).reshape(d, d) + ridge for _ in range(k)])
    weights = np.full(k, 1.0 / k)
    previous = -np.inf
    for _ in range(iterations):
        log_p = np.stack([_log_normal(x, means[j], covs[j]) for j in range(k)], axis=1) + np.log(weights)
        top = log_p.max(axis=1, keepdims=True)
        log_total = top[:, 0] + np.log(np.exp(log_p - top).sum(axis=1))
        resp = np.exp(log_p - log_total[:, None])
        likelihood = float(log_total.sum())
        nk = resp.sum(axis=0) + 1e-12
        weights = nk / n
        means = (resp.T @ x) / nk[:, None]
        covs = np.array([((resp[:, j, None] * (x - means[j])).T @ (x - means[j])) / nk[j] + ridge for j in range(k)])
        if likelihood - previous < 1e-8 * abs(likelihood):
            break
        previous = likelihood
    return weights, means, covs, likelihood


def _log_normal(x: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> np.ndarray:
    d = x.shape[1]
    sign, logdet = np.linalg.slogdet(cov)
    diff = x - mean
    return -0.5 * (np.einsum("ni,ij,nj->n", diff, np.linalg.inv(cov), diff) + logdet + d * np.log(2 * np.pi))


def classify_gaussians(
    masses: np.ndarray,
    sigmas_A: np.ndarray,
    positions_A: np.ndarray,
    max_classes: int = MAX_CLASSES,
    device: str | torch.device = "cpu",
) -> Classification:
    """Classes and support of N fitted Gaussians (module docstring).

    Parameters
    ----------
    masses : (N,) positive
        Integrated potentials, any unit.
    sigmas_A : (N,) positive
        Widths, Å.
    positions_A : (N, 3)
        Å.
    device : str or torch.device
        Where the mixture is fitted (:func:`gaussian_mixture`).
    """
    masses = np.asarray(masses, dtype=np.float64)
    positions = np.asarray(positions_A, dtype=np.float64).reshape(-1, 3)
    if len(masses) == 0:
        return Classification(np.zeros(0, dtype=np.int64), np.zeros(0, dtype=bool), np.zeros((0, 2)), {})
    classes, class_means, bic = mixture_classes(masses, sigmas_A, max_classes, device)
    support = in_support(positions)
    return Classification(classes, support & population_support(classes, support, masses, positions), class_means, bic)


def mixture_classes(
    masses: np.ndarray, sigmas_A: np.ndarray, max_classes: int = MAX_CLASSES, device: str | torch.device = "cpu"
) -> tuple[np.ndarray, np.ndarray, dict]:
    """The classes of N > 0 Gaussians by (log mass, log width) (module docstring): (N,) each one's
    class (1..k, by increasing mean mass), (k, 2) the classes' means and the information
    criterion of each number of classes tried."""
    masses, sigmas = np.asarray(masses, dtype=np.float64), np.asarray(sigmas_A, dtype=np.float64)
    n = len(masses)
    x = np.stack([np.log(np.maximum(masses, 1e-300)), np.log(np.maximum(sigmas, 1e-300))], axis=1)
    best, bic = None, {}
    for k in range(1, min(max_classes, max(n // 10, 1)) + 1):  # ten Gaussians a class at least
        starts = [gaussian_mixture(x, k, seed=seed, device=device) for seed in range(MIXTURE_STARTS if k > 1 else 1)]
        weights, means, covs, likelihood = max(starts, key=lambda fit: fit[3])  # the first of equals
        parameters = k * (2 + 3) + (k - 1)
        bic[k] = -2.0 * likelihood + parameters * np.log(n)
        if best is None or bic[k] < bic[best[0]]:
            best = (k, weights, means, covs)
    k, weights, means, covs = best
    log_p = (
        _log_normals(torch.as_tensor(x.T.copy()), torch.as_tensor(means), torch.as_tensor(covs)).numpy()
        + np.log(weights)[:, None]
    ).T
    order = np.argsort(means[:, 0])
    rank = np.empty(k, dtype=np.int64)
    rank[order] = np.arange(1, k + 1)
    return rank[np.argmax(log_p, axis=1)], means[order], bic


def population_support(
    classes: np.ndarray, support: np.ndarray, masses: np.ndarray, positions_A: np.ndarray
) -> np.ndarray:
    """(N,) bool: False for every member of a class that lies outside the confident atoms' support
    (module docstring).  The confident atoms: the supported members of the class that holds the
    most mass among the supported Gaussians (:func:`confident_class`).  A member lies outside when
    no confident atom other than itself is within the far-out fence (:data:`FENCE_IQR`) of the
    confident atoms' nearest-neighbour distances (:func:`near_confident`); a class lies outside
    when more than half its members do."""
    classes, support = np.asarray(classes), np.asarray(support, dtype=bool)
    keep = np.ones(len(classes), dtype=bool)
    confident = confident_class(classes, support, masses)
    near = None if confident is None else near_confident(classes, support, positions_A, confident)
    if near is None:
        return keep
    for c in np.unique(classes[support]):
        if c != confident and np.mean(near[classes == c]) < 0.5:
            keep[classes == c] = False
    return keep


def confident_class(classes: np.ndarray, support: np.ndarray, masses: np.ndarray) -> int | None:
    """The class holding the most mass among the supported Gaussians (:func:`population_support`);
    None where fewer than two classes have supported members."""
    classes, support = np.asarray(classes), np.asarray(support, dtype=bool)
    labels = np.unique(classes[support])
    if len(labels) < 2:
        return None
    mass = np.asarray(masses, dtype=np.float64)
    return int(labels[np.argmax([mass[support & (classes == c)].sum() for c in labels])])


def near_confident(
    classes: np.ndarray, support: np.ndarray, positions_A: np.ndarray, confident: int
) -> np.ndarray | None:
    """(N,) bool: a confident atom (a supported member of class ``confident``) other than itself
    lies within the far-out fence (:data:`FENCE_IQR`) of the confident atoms' nearest-neighbour
    distances; None where fewer than four confident atoms say what those distances are."""
    positions = np.asarray(positions_A, dtype=np.float64).reshape(-1, 3)
    confident_atoms = np.flatnonzero(np.asarray(support, dtype=bool) & (np.asarray(classes) == confident))
    if len(confident_atoms) < 4:
        return None
    d = nearest_neighbour_distances(positions[confident_atoms])
    q1, q3 = np.percentile(d, [25, 75])
    distance, index = cKDTree(positions[confident_atoms]).query(positions, k=2, workers=-1)
    # a confident atom's nearest confident atom is itself: take the second
    own = confident_atoms[index[:, 0]] == np.arange(len(positions))
    return np.where(own, distance[:, 1], distance[:, 0]) <= q3 + FENCE_IQR * (q3 - q1)


def in_support(positions_A: np.ndarray) -> np.ndarray:
    """(N,) bool: at least two neighbours within the far-out fence of all the nearest-neighbour
    distances (:data:`FENCE_IQR`) or twice their median; every position with fewer than four in all."""
    positions = np.asarray(positions_A, dtype=np.float64).reshape(-1, 3)
    if len(positions) < 4:
        return np.ones(len(positions), dtype=bool)
    d = nearest_neighbour_distances(positions)
    q1, q3 = np.percentile(d, [25, 75])
    radius = max(q3 + FENCE_IQR * (q3 - q1), 2.0 * float(np.median(d)))
    # itself and two more
    return cKDTree(positions).query_ball_point(positions, radius, return_length=True, workers=-1) >= 3
