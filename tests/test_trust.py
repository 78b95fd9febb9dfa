"""Which atoms a run leaves open (atoms/trust.py): a mass unlike one atom of its element, a depth
the views fix far less well than its element's, and the columns that open an atom; float64,
thresholds from the proof level."""

import numpy as np

from gaussian_atoms_method.atoms.atom_set import AtomSet
from gaussian_atoms_method.atoms.calibration import Z95
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


def test_an_atom_whose_depth_the_views_fix_far_less_than_its_elements_and_not_beyond_doubt_is_open_in_depth():
    """Pd and Pt atoms whose rise one step along the beam scatters log-normally by 25% about 200
    and 1,000 stated variances (the rise goes as the mass squared, so each element is its own
    population), at the proof level for 8,000 atoms (4.5; the normal's tail beyond it is 3e-6,
    so no right atom by chance).  Open: a Pt atom at 15 (far below Pt, under 4.5^2 = 20; pooled
    with Pd it looks ordinary) and a negative rise (the views prefer the other place).  A Pd atom
    at 40 is far below Pd but excluded at the proof level; a floor along the beam that makes the
    stated variance 0.4 of the widened one reads it as 16, and opens it.  A rise above the median
    and a NaN (no profile) never open."""
    rng = np.random.default_rng(2)
    species = np.repeat(["Pd", "Pt"], 4000)
    rise = np.repeat([200.0, 1000.0], 4000) * np.exp(rng.normal(0, 0.25, 8000))
    rise[[10, 4010, 20, 30, 50]] = [40.0, 15.0, 300.0, np.nan, -3.0]
    level = proof_level(len(rise))
    assert np.flatnonzero(depth_unlike_its_element(rise, level, species)).tolist() == [50, 4010]
    assert not depth_unlike_its_element(rise, level)[4010]  # pooled with Pd, the Pt atom's rise looks ordinary
    half = np.full(len(rise), 0.1)
    floor_z = 0.1 * np.sqrt(0.6) / Z95  # (Z95 floor / half)^2 = 0.6 of the widened variance
    widened = depth_unlike_its_element(rise, level, species, half, floor_z)
    assert np.flatnonzero(widened).tolist() == [10, 50, 4010]
