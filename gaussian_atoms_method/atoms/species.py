"""Species from the fitted Gaussians: heavier elements scatter more, so an atom's integrated
potential (its Gaussian's mass, ``amplitude (2 pi sigma^2)^(3/2)``) grows with atomic number.

:func:`classify_species` clusters the logarithm of the masses into as many groups as elements
(1D k-means started at quantiles), and gives the heaviest group the heaviest element.  The
separation of neighbouring groups is reported as ``d' = (mean_b - mean_a) / sqrt((var_a +
var_b) / 2)`` on log mass: above about 3 the groups barely overlap.
"""

from __future__ import annotations

import numpy as np


def _atomic_number(symbol: str) -> int:
    from ase.data import atomic_numbers

    if symbol not in atomic_numbers:
        raise ValueError(f"unknown element {symbol!r} in --species")
    return atomic_numbers[symbol]


ADF_STEEPEST_EXPONENT = 2.0
"""The steepest a projected atom's integrated intensity grows with atomic number: ``Z^2``,
unscreened Rutherford scattering (ADF-STEM's ``Z^1.6-1.9``, a projected potential's slower)."""


def lightest_mass_ratio(elements) -> float:
    """The least integrated mass an atom of the lightest of ``elements`` can have against one of
    the heaviest, whatever the contrast: ``(Z_min / Z_max)^2`` (:data:`ADF_STEEPEST_EXPONENT`);
    1 for one element or none.

    >>> round(lightest_mass_ratio(["Ni", "Pd", "Pt"]), 3), lightest_mass_ratio(["Ta"])
    (0.129, 1.0)
    """
    numbers = [_atomic_number(e) for e in elements]
    return (min(numbers) / max(numbers)) ** ADF_STEEPEST_EXPONENT if numbers else 1.0


def kmeans_1d(values: np.ndarray, k: int, iterations: int = 100) -> np.ndarray:
    """Labels 0..k-1 of a 1D k-means of ``values``, ordered by increasing cluster mean."""
    values = np.asarray(values, dtype=np.float64)
    centres = np.quantile(values, (np.arange(k) + 0.5) / k)
    labels = np.zeros(len(values), dtype=np.int64)
    for _ in range(iterations):
        labels = np.argmin(np.abs(values[:, None] - centres[None, :]), axis=1)
        new = np.array([values[labels == j].mean() if np.any(labels == j) else centres[j] for j in range(k)])
        if np.allclose(new, centres):
            break
        centres = new
    order = np.argsort(centres)
    return np.argsort(order)[labels]


ELEMENT_OPEN_BELOW = 0.95
"""An atom's element is open where its probability (``element_confidence``) is under this: the
level of the run's other statements (95% intervals)."""

ASHMAN_D = 2.0
"""Two normal populations are separate when their means lie more than this many pooled standard
deviations apart (Ashman's D, K. M. Ashman, C. M. Bird and S. E. Zepf, Astron. J. 108, 2348
(1994): a mixture of two normals with D > 2 is cleanly bimodal)."""
MIN_PER_POPULATION = 10
"""A population needs this many atoms to be told from the scatter of another."""


def mass_populations(log_masses: np.ndarray, k: int) -> tuple[int, str]:
    """How many separate populations, at most ``k``, the (N,) log masses hold: the number of
    components of a Gaussian mixture that the Bayesian information criterion picks (1..k, each
    with :data:`MIN_PER_POPULATION` atoms at least), less one for each neighbouring pair of
    components closer than :data:`ASHMAN_D`.  Returns the number and the test as a sentence.

    Why not k-means alone: it splits one normal population at its median into halves whose
    separation reads 2.65 standard deviations, so a pure Au particle exported with ``Fe,Pt``
    came out as Fe and Pt."""
    from gaussian_atoms_method.atoms.classification import gaussian_mixture

    x = np.asarray(log_masses, dtype=np.float64).reshape(-1, 1)
    n = len(x)
    best, fits = 1, {}
    for j in range(1, min(k, max(n // MIN_PER_POPULATION, 1)) + 1):
        weights, means, covs, likelihood = gaussian_mixture(x, j)
        fits[j] = (-2.0 * likelihood + (3 * j - 1) * np.log(n), means[:, 0], covs[:, 0, 0], weights)
        if fits[j][0] < fits[best][0]:
            best = j
    _, means, variances, _ = fits[best]
    order = np.argsort(means)
    d = np.diff(means[order]) / np.sqrt((variances[order][1:] + variances[order][:-1]) / 2.0)
    populations = 1 + int(np.sum(d > ASHMAN_D))
    said = f"a Gaussian mixture on log mass picks {best} component(s) by BIC" + (
        f", Ashman's D between neighbours {', '.join(f'{v:.2f}' for v in d)} (separate above {ASHMAN_D:g})"
        if best > 1
        else ""
    )
    return populations, said


def classify_species(masses: np.ndarray, elements: list[str]) -> tuple[np.ndarray, dict]:
    """Assign each atom one of ``elements`` by its integrated mass.

    Parameters
    ----------
    masses : (N,) positive array
    elements : element symbols, any order (e.g. ``["Fe", "Pt"]``)

    Returns
    -------
    species : (N,) array of str
    report : dict with the count, mean log-mass of each element and the separations ``d'``
        between neighbouring elements (by atomic number); ``separated`` False, and every atom
        the heaviest element given, where the masses do not hold as many separate populations
        as elements (:func:`mass_populations`); ``confidence`` (N,) each atom's probability of
        the element it is given (:func:`element_posteriors`; 1 with one element, NaN where the
        populations are not separate)

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> masses = np.exp(np.r_[rng.normal(0.0, 0.1, 50), rng.normal(1.0, 0.1, 50), 0.5])
    >>> species, report = classify_species(masses, ["Pt", "Co"])
    >>> species[-1], round(float(report["confidence"][-1]), 1), bool(np.median(report["confidence"]) > 0.99)
    (np.str_('Co'), 0.5, True)
    """
    masses = np.asarray(masses, dtype=np.float64)
    if len(elements) == 0:
        raise ValueError("--species needs at least one element")
    if np.any(~np.isfinite(masses)) or np.any(masses <= 0):
        raise ValueError("atom masses must be positive and finite to classify species")
    ordered = sorted(elements, key=_atomic_number)
    if len(ordered) == 1 or len(masses) < len(ordered):
        confidence = np.full(len(masses), 1.0 if len(ordered) == 1 else np.nan)
        return np.array([ordered[-1]] * len(masses)), {"counts": {ordered[-1]: len(masses)}, "confidence": confidence}
    logm = np.log(masses)
    populations, test = mass_populations(logm, len(ordered))
    if populations < len(ordered):
        return np.array([ordered[-1]] * len(masses)), {
            "counts": {ordered[-1]: len(masses)},
            "separated": False,
            "populations": populations,
            "test": test,
            "confidence": np.full(len(masses), np.nan),
        }
    # the populations from k-means; each atom the element Bayes' rule makes most probable (the
    # least error: k-means's nearest centre ignores that one population is wider than another)
    posterior = element_posteriors(logm, kmeans_1d(logm, len(ordered)))
    labels = np.argmax(posterior, axis=1)
    species = np.array(ordered)[labels]
    report = {
        "counts": {},
        "mean_log_mass": {},
        "separation": {},
        "separated": True,
        "populations": populations,
        "test": test,
        "confidence": posterior[np.arange(len(labels)), labels],
    }
    for j, el in enumerate(ordered):
        report["counts"][el] = int(np.sum(labels == j))
        report["mean_log_mass"][el] = float(logm[labels == j].mean()) if np.any(labels == j) else float("nan")
    for j in range(len(ordered) - 1):
        a, b = logm[labels == j], logm[labels == j + 1]
        pooled = np.sqrt((a.var() + b.var()) / 2) if len(a) > 1 and len(b) > 1 else float("nan")
        report["separation"][f"{ordered[j]}/{ordered[j + 1]}"] = (
            float((b.mean() - a.mean()) / pooled) if pooled > 0 else float("inf")
        )
    return species, report


def element_posteriors(log_masses: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """(N, k) each atom's probability of each of the k populations ``labels`` (0..k-1) splits the
    (N,) log masses into: a mixture of normals, each population's share, median and spread its
    atoms' (Bayes' rule on the atom's log mass).  The spread is the median absolute deviation
    (times 1.4826, a normal's standard deviation), so the atoms between two populations do not
    widen the one they were put in; a population too small to show one takes the others'."""
    x = np.asarray(log_masses, dtype=np.float64)
    k = int(labels.max()) + 1
    groups = [x[labels == j] for j in range(k)]
    spread = [1.4826 * np.median(np.abs(g - np.median(g))) if len(g) > 2 else 0.0 for g in groups]
    fallback = np.median([s for s in spread if s > 0] or [np.std(x) or 1.0])
    log_p = np.stack(
        [
            np.log(len(g) / len(x)) - np.log(s) - 0.5 * ((x - np.median(g)) / s) ** 2
            for g, s in zip(groups, (s if s > 0 else fallback for s in spread))
        ],
        axis=1,
    )
    log_p -= log_p.max(axis=1, keepdims=True)
    p = np.exp(log_p)
    return p / p.sum(axis=1, keepdims=True)


def open_elements_words(confidence: np.ndarray) -> str:
    """The part of the species line that counts the atoms whose element is open
    (:data:`ELEMENT_OPEN_BELOW`); "" where there are none.

    >>> open_elements_words(np.array([1.0, 0.6, 0.99]))
    '; 1 atom open in element (probability under 0.95)'
    """
    n = int(np.sum(np.asarray(confidence) < ELEMENT_OPEN_BELOW))
    return f"; {n} atom{'s' if n != 1 else ''} open in element (probability under {ELEMENT_OPEN_BELOW:g})" if n else ""


def one_population_note(report: dict, element: str) -> str:
    """The line said where :func:`classify_species` found fewer mass populations than elements
    (``report["separated"]`` False) and wrote every atom as ``element``."""
    return (
        f"gaussian-atoms: the atoms' masses show {report['populations']} separate population(s), not one per "
        f"element ({report['test']}): every atom written as {element}"
    )
