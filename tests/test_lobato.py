"""Lobato's projected potentials from their parameters (physics/lobato.py): the profile a run's own
replica draws its atoms with, with no simulator installed."""

import numpy as np
import pytest
from scipy.integrate import quad

from gaussian_atoms_method.physics.lobato import KAPPA, _table, lobato_parameters, lobato_projected_potential_VA


@pytest.mark.parametrize("element", ["H", "C", "Ni", "Ta", "Pt", "Lr"])
def test_a_projected_potential_integrates_to_the_scattering_factor_at_zero_over_kappa(element):
    """The projected potential's integral over the plane is its transform at zero spatial frequency,
    the scattering factor ``f(0) = sum 2 a_i`` (Å) turned into a potential by ``kappa``: a check of
    the closed form (the K0 and K1 terms, the scaled parameters) that needs no other code.  The
    quadrature holds it to 1e-9 (the K0 core is integrable: ``r log r`` vanishes at 0)."""
    a, _ = lobato_parameters(element)
    integral = quad(lambda r: 2 * np.pi * r * lobato_projected_potential_VA(element, np.array(r)), 0, 60, limit=500)[0]
    assert integral == pytest.approx(2 * a.sum() / KAPPA, rel=1e-9)


def test_every_element_falls_off_from_a_sharp_core_into_tails():
    """A neutral atom's projected potential is positive and falls monotonically with the radius over
    0.001-8 Å, for every element of the table (H to Lr)."""
    r = np.geomspace(1e-3, 8.0, 400)
    for element in _table():
        v = lobato_projected_potential_VA(element, r)
        assert np.all(v > 0) and np.all(np.diff(v) < 0), element


def test_an_unknown_element_is_named():
    with pytest.raises(ValueError, match="'Xx'"):
        lobato_parameters("Xx")


def test_the_profiles_are_abtems_where_abtem_is_installed():
    """The same table and closed form as abTEM's: every element within 1e-4 of its peak over
    0.0001-12 Å.  abTEM evaluates in float32, and some elements' terms cancel (He: a_i of -62 and
    +64), which costs it 6e-5 of the peak; all others agree within 7e-6."""
    parametrizations = pytest.importorskip("abtem.parametrizations")
    r = np.geomspace(1e-4, 12.0, 500)
    for element in _table():
        theirs = np.asarray(parametrizations.LobatoParametrization().projected_potential(element)(r), dtype=np.float64)
        ours = lobato_projected_potential_VA(element, r)
        assert np.max(np.abs(ours - theirs)) <= 1e-4 * theirs.max(), element


def test_a_run_draws_its_own_replica_without_abtem(monkeypatch):
    """The own floor's replica needs no simulator: with abTEM unimportable, a run with its elements
    given draws them as named, an atom of no element as the most common element, a run with none
    named as the stand-in, and an ADF kernel is still formed, unit at zero frequency and falling
    (its float64 transform against the cached one within 1e-6)."""
    import sys

    from gaussian_atoms_method.engine.own_floor import STAND_IN_ELEMENT, drawable_species
    from gaussian_atoms_method.physics.adf import adf_kernel_transform

    monkeypatch.setitem(sys.modules, "abtem", None)
    named, words = drawable_species(np.array(["Ta", "Pt"]), 2)
    assert list(named) == ["Ta", "Pt"] and words == ""
    assert list(drawable_species(np.array(["Ta", "X", "Pt", "Ta"]), 4)[0]) == ["Ta", "Ta", "Pt", "Ta"]
    assert set(drawable_species(np.array(["X", "X"]), 2)[0]) == set(drawable_species(None, 2)[0]) == {STAND_IN_ELEMENT}
    k, transfer = adf_kernel_transform.__wrapped__("Pt")
    assert transfer[0] == pytest.approx(1.0) and transfer[-1] < 0.5
    assert np.allclose(transfer, adf_kernel_transform("Pt")[1], atol=1e-6)
