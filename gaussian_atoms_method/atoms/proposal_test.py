"""How strongly the residuals ask for one more atom at a place, its neighbours re-fitted.

An atom of typical width and peak at ``p`` adds the template ``g_p`` to the views.  At the fit's
optimum the residual ``r`` is orthogonal to every neighbour's derivatives, so what the data say
for an atom at ``p`` is the score ``s = <g_p, r>`` against the part of ``g_p`` the neighbours
cannot take up: ``z = s / (noise sqrt(I_eff))`` with ``I_eff = I_pp - I_pS I_SS^-1 I_Sp`` (the
information of its amplitude less what its neighbours' five parameters each share with it: Rao's
score test with the neighbours re-fitted, normal under the null where the model holds).  The
plain score ``s / (noise sqrt(I_pp))`` is what a residual search reads; where neighbours have
taken up a missed atom's mass the two part.  On carbon phase images at 2,000 e/Å² (the 475
atoms the fit missed): the neighbours could take up 95% of a missed atom's information (median);
``z`` reached a median 8.8 at the open places within 0.75 Å of a missed atom, -1.9 at those of
an 11 Å Au particle the fit had found whole (the plain score: 2.1 and -1.3).  Where the fit's
atom is not the data's, ``z`` also reaches the proof level at places that ask for a fraction of
an atom (the aSi-208 counts at 1.6e5: 53 places asking for a median 0.07 atoms' mass), so a
place is proven to hold an atom where ``z`` less half the ``z`` of a whole atom reaches it: the
residuals ask for more than half an atom there, nearer one than none.
"""

from __future__ import annotations

import itertools

import numpy as np
from scipy.spatial import cKDTree

from gaussian_atoms_method.atoms.information import pair_information, view_scores

REACH_WIDTHS = 6.0
"""Neighbours within this many of the atoms' median width share information with the place:
two Gaussian images of width ``s`` a distance ``d`` apart overlap by ``exp(-d^2 / 4 s^2)`` of
their peaks' product, under 1e-4 beyond six widths."""


def proposal_significance(
    places_A: np.ndarray,
    positions_A: np.ndarray,
    sigmas_A: np.ndarray,
    amplitudes: np.ndarray,
    detector_axes: np.ndarray,
    residuals,
    pixel_size_A: float,
    centre_px,
    noise_std: float,
    amplitude_factor: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Two (M,): ``z`` of an atom of the median width and peak ``q`` at each of ``places_A``
    (M, 3), and the ``z`` a whole such atom missing there would read (``q sqrt(I_eff) / noise``:
    ``z`` over it is the share of an atom's mass the residuals ask for there), with
    the atoms ``positions_A`` (N, 3; Å about the tilt centre), ``sigmas_A`` and ``amplitudes``
    (N,) re-fitted (module docstring).  ``residuals`` (V, H, W): measured minus predicted,
    in the amplitudes' projection units; ``noise_std`` their pixel standard deviation and
    ``amplitude_factor`` their weight at an atom's scale against white noise
    (:func:`~.information.residual_spectrum_factors`).

    >>> axes = np.array([[[1.0, 0, 0], [0, 1, 0]], [[0, 0, 1.0], [0, 1, 0]]])
    >>> residuals = np.zeros((2, 9, 9))
    >>> z, whole = proposal_significance(np.zeros((1, 3)), np.array([[2.0, 0, 0]]), np.ones(1), np.ones(1),
    ...                           axes, residuals, 0.5, (4, 4), 1.0)
    >>> z.tolist(), bool(whole[0] > 0)
    ([0.0], True)
    """
    places = np.asarray(places_A, np.float64).reshape(-1, 3)
    positions = np.asarray(positions_A, np.float64).reshape(-1, 3)
    sig, amp = np.asarray(sigmas_A, np.float64), np.asarray(amplitudes, np.float64)
    m = len(places)
    if m == 0 or len(positions) == 0:
        return np.zeros(m), np.zeros(m)
    s0, q0 = float(np.median(sig)), float(np.median(amp))
    ones = np.ones(m)
    score = view_scores(places, s0 * ones, q0 * ones, detector_axes, residuals, pixel_size_A, centre_px).sum(1)[:, 4]
    own = pair_information(places, places, s0 * ones, s0 * ones, q0 * ones, q0 * ones, detector_axes, pixel_size_A)
    near = cKDTree(positions).query_ball_point(places, REACH_WIDTHS * s0)
    # every block the places' systems need, each read once
    counts = np.fromiter(map(len, near), np.int64, count=m)
    place_of = np.repeat(np.arange(m), counts)
    atom_of = np.fromiter(itertools.chain.from_iterable(near), np.int64, count=int(counts.sum()))
    cross = pair_information(
        places[place_of], positions[atom_of], s0 * np.ones(len(place_of)), sig[atom_of], q0 * np.ones(len(place_of)),
        amp[atom_of], detector_axes, pixel_size_A,
    )[:, 4, :]  # fmt: skip
    n = len(positions)
    start = np.r_[0, np.cumsum(counts)]
    groups = {int(k): np.nonzero(counts == k)[0] for k in np.unique(counts[counts > 0])}
    # each place's neighbours as a row, the places of one count together (G, k): atom_of in place order
    rows = {k: atom_of[start[which][:, None] + np.arange(k)] for k, which in groups.items()}
    within = [np.zeros((0, 2), np.int64)]
    for k, a in rows.items():  # each place's pairs (i <= j) among its neighbours
        i, j = np.triu_indices(k)
        within.append(np.stack([a[:, i].ravel(), a[:, j].ravel()], 1))
    within = np.concatenate(within)
    keys = np.unique(within[:, 0] * n + within[:, 1])  # sorted
    pairs = np.stack([keys // n, keys % n], axis=1)
    blocks = pair_information(
        positions[pairs[:, 0]], positions[pairs[:, 1]], sig[pairs[:, 0]], sig[pairs[:, 1]], amp[pairs[:, 0]],
        amp[pairs[:, 1]], detector_axes, pixel_size_A,
    )  # fmt: skip
    shared = np.zeros(m)
    for k, which in groups.items():  # the places with k neighbours, their systems at once
        atoms = rows[k]  # (G, k)
        i, j = atoms[:, :, None], atoms[:, None, :]
        lo, hi = np.minimum(i, j), np.maximum(i, j)
        found = blocks[np.searchsorted(keys, lo * n + hi)]  # (G, k, k, 5, 5), rows: the lower index
        system = np.where((i <= j)[..., None, None], found, found.swapaxes(-1, -2))
        system = system.transpose(0, 1, 3, 2, 4).reshape(len(which), 5 * k, 5 * k)
        c = cross[start[which][:, None] + np.arange(k)].reshape(len(which), 5 * k)  # (G, 5k)
        # a neighbour's parameters may be all but degenerate
        ridge = 1e-9 * np.trace(system, axis1=1, axis2=2)[:, None, None] / (5 * k) * np.eye(5 * k)
        shared[which] = np.einsum("gi,gi->g", c, np.linalg.solve(system + ridge, c[..., None])[..., 0])
    efficient = np.maximum(own[:, 4, 4] - shared, 1e-12 * own[:, 4, 4])
    scale = noise_std * amplitude_factor * np.sqrt(efficient)
    return score / scale, q0 * efficient / scale
