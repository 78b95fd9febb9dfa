"""Which atoms a run leaves open (atoms/trust.py): a mass unlike one atom of its element, a depth
the views fix far less well than its element's, and the columns that open an atom; float64,
thresholds from the proof level."""

import numpy as np

from gaussian_atoms_method.atoms.atom_set import AtomSet
from gaussian_atoms_method.atoms.evidence import proof_level
from gaussian_atoms_method.atoms.trust import depth_unlike_its_element, mass_unlike_one_atom, open_atoms, trust_words


def test_a_gaussian_holding_two_atoms_or_half_of_one_is_unlike_one_atom_and_the_rest_are_not():
    """10,000 single atoms whose log mass scatters normally by 8% (noise and neighbours' loans),
    one Gaussian of two atoms' mass (+69%, 8.7 spreads) and one of half an atom's (-69%): at the
    proof level (4.6 for 10,002 atoms) the two are open and, by the level's family-wise 5%, at most
    a few of the single atoms (the normal's two-sided tail beyond 4.6 is 4e-6: 0.04 expected)."""
    rng = np.random.default_rng(0)
    masses = np.exp(rng.normal(0.0, 0.08, 10_000))
    masses = np.r_[masses, 2.0, 0.5]
    level = proof_level(len(masses))
    unlike = mass_unlike_one_atom(masses, level)
    assert unlike[-2:].all()
    assert unlike[:-2].sum() <= 1


def test_each_element_is_its_own_mass_reference():
    """Ni, Pd and Pt populations (ADF masses about 0.16 : 0.4 : 1, 6% scatter each): no atom of
    any is unlike its own element, though Pt lies 14 of the pooled population's spreads from its
    median; a Pd Gaussian holding a Ni atom too (+40%) is."""
    rng = np.random.default_rng(1)
    species = np.repeat(["Ni", "Pd", "Pt"], 1000)
    masses = np.repeat([0.16, 0.4, 1.0], 1000) * np.exp(rng.normal(0, 0.06, 3000))
    masses[1500] = 0.4 * 1.4
    level = proof_level(len(masses))
    unlike = mass_unlike_one_atom(masses, level, species)
    assert np.flatnonzero(unlike).tolist() == [1500]
    assert mass_unlike_one_atom(masses, level).sum() == 0  # pooled, the populations hide it


def test_an_atom_of_a_mass_unlike_one_atom_is_open_and_said():
    atoms = AtomSet(
        np.zeros((3, 3)),
        proven=[1, 1, 1],
        depth_open=[0, 0, 0],
        width_open=[0, 0, 0],
        mass_open=[0, 1, 0],
        info={"proof_level": 3.6},
        significance=[9.0, 8.0, 7.0],
    )
    assert open_atoms(atoms).tolist() == [False, True, False]
    assert "1 of a mass unlike one atom of their element" in trust_words(atoms)


def test_an_atom_whose_depth_the_views_fix_far_less_than_its_elements_is_open_in_depth():
    """Pd and Pt atoms whose rise one step along the beam scatters log-normally by 25% about 100
    and 600 stated variances (the rise goes as the mass squared, so each element is its own
    population): a Pd atom at 25 (a column that could shift) and a Pt atom at 100 (five spreads
    below Pt, though Pd's median) are open, at the proof level for 8,002 atoms (4.5; the normal's
    tail beyond it is 3e-6, so no right atom by chance); a rise above the median, a NaN (no
    profile) and a Pd atom at 60 (two spreads) are not; a negative rise (the views prefer the
    other place) is."""
    rng = np.random.default_rng(2)
    species = np.repeat(["Pd", "Pt"], 4000)
    rise = np.repeat([100.0, 600.0], 4000) * np.exp(rng.normal(0, 0.25, 8000))
    rise[[10, 4010, 20, 30, 40, 50]] = [25.0, 100.0, 300.0, np.nan, 60.0, -3.0]
    level = proof_level(len(rise) + 2)
    unlike = depth_unlike_its_element(rise, level, species)
    assert np.flatnonzero(unlike).tolist() == [10, 50, 4010]
    pooled = depth_unlike_its_element(rise, level)
    assert not pooled[4010]  # pooled with Pd, the Pt atom's rise looks ordinary
