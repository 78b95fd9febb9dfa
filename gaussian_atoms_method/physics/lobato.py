"""Lobato and Van Dyck's projected atomic potentials, read from their published parameters with
no simulator installed.

A run's own precision floor (:mod:`~gaussian_atoms_method.engine.own_floor`) draws its atoms
through physics the fit does not share: each atom's ADF image a power of its element's projected
potential (:func:`.adf.adf_kernel_transform`).  That needs only the potential's radial profile,
five terms per element in closed form, so it is computed here from the parameters rather than
through abTEM: the floor then runs wherever the fit runs (a GPU image, a cluster) and not only
where the optional simulator is installed.

The parameters (``data/lobato_2014.json``) are Lobato and Van Dyck's fit of each element's
electron scattering factor, ``f(g) = sum_i a_i (2 + b_i g^2) / (1 + b_i g^2)^2`` (g in 1/Å), for
H to Lr (I. Lobato and D. Van Dyck, Acta Cryst. A70 (2014) 636-649), as abTEM distributes them.
"""

from __future__ import annotations

import functools
import json
from importlib import resources

import numpy as np
from scipy.special import k0, k1

KAPPA = 0.0208865737082965
"""``4 pi eps0 / (2 pi a0 e)`` = ``2 eps0 / (a0 e)`` (eps0 in F/Å, the Bohr radius a0 in Å, e in C):
the factor that turns a scattering factor (Å) into a potential (V·Å³ for the 3D potential,
V·Å for the projected one).  CODATA 2018; abTEM's ``kappa`` to the printed digits."""


@functools.cache
def _table() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    text = resources.files("gaussian_atoms_method.physics").joinpath("data/lobato_2014.json").read_text()
    return {
        symbol: (np.array(a, dtype=np.float64), np.array(b, dtype=np.float64))
        for symbol, (a, b) in json.loads(text).items()
    }


def lobato_parameters(element: str) -> tuple[np.ndarray, np.ndarray]:
    """(a (5,) Å, b (5,) Å²): Lobato and Van Dyck's parameters of ``element`` (module text).

    >>> a, b = lobato_parameters("Ta")
    >>> a.shape, bool((b > 0).all())
    ((5,), True)
    """
    table = _table()
    if element not in table:
        raise ValueError(f"no Lobato parameters for element {element!r} (H to Lr)")
    return table[element]


def lobato_projected_potential_VA(element: str, r_A: np.ndarray) -> np.ndarray:
    """The projected potential (V·Å) of one neutral atom of ``element`` at radii ``r_A`` (any
    shape, Å, > 0): the scattering factor's five terms transformed to real space and integrated
    along the beam, ``2 sum_i [2 a'_i / b'_i K0(b'_i r) + a'_i r K1(b'_i r)]`` with
    ``a'_i = pi^2 a_i / b_i^(3/2) / kappa`` and ``b'_i = 2 pi / sqrt(b_i)``.

    A sharp core (``K0`` diverges as ``-log r``) and tails that fall as ``exp(-b' r)``: the atom
    a Gaussian fit does not draw.

    >>> v = lobato_projected_potential_VA("Ta", np.array([0.1, 1.0, 3.0]))
    >>> bool(v[0] > v[1] > v[2] > 0)
    True
    """
    a, b = lobato_parameters(element)
    scaled_a = np.pi**2 * a / b**1.5 / KAPPA
    scaled_b = 2 * np.pi / np.sqrt(b)
    r = np.asarray(r_A, dtype=np.float64)[..., None]
    terms = 2 * scaled_a / scaled_b * k0(r * scaled_b) + scaled_a * r * k1(r * scaled_b)
    return 2 * terms.sum(-1)
