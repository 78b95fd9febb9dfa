"""The replica's probe (physics/probe_width.py): the source that makes one atom as wide as the fit
reads it, solved back from the width it gives."""

import dataclasses

import pytest

from gaussian_atoms_method.physics.microscope import DEFAULT_OPTICS
from gaussian_atoms_method.physics.probe_width import fitted_atom_width_A, probe_as_wide_as


@pytest.mark.parametrize("element", ["C", "Pd", "Au"])
@pytest.mark.parametrize("source_fwhm_A", [0.3, 0.7, 1.2])
def test_the_source_is_solved_back_from_the_width_it_gives(element, source_fwhm_A):
    """The bisection stops within 1e-3 Å of source; the width grows with the source by at least
    0.05 Å per Å here, so the source comes back to 0.01 Å."""
    optics = dataclasses.replace(DEFAULT_OPTICS, source_fwhm_A=source_fwhm_A)
    width = fitted_atom_width_A(element, optics)
    assert probe_as_wide_as(element, width, DEFAULT_OPTICS).source_fwhm_A == pytest.approx(source_fwhm_A, abs=0.01)


def test_an_atom_narrower_than_the_bare_probe_gets_no_source_and_a_wider_source_a_wider_atom():
    """A width under the aberrated probe's own (no source) cannot be reached: no source, the
    replica's atoms then wider than the views'.  The least-squares width grows with the source."""
    bare = fitted_atom_width_A("C", dataclasses.replace(DEFAULT_OPTICS, source_fwhm_A=0.0))
    assert probe_as_wide_as("C", 0.5 * bare, DEFAULT_OPTICS).source_fwhm_A == 0.0
    widths = [fitted_atom_width_A("C", dataclasses.replace(DEFAULT_OPTICS, source_fwhm_A=s)) for s in (0, 0.5, 1, 2)]
    assert widths == sorted(widths) and widths[-1] > widths[0] + 0.3
