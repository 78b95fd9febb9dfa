"""Noise drawn with both of a run's readings (physics/correlated_noise.py): its neighbouring
pixels read the variance asked for, and what neighbouring views do not share reads the factor
asked for over an atom."""

import numpy as np
import pytest

from gaussian_atoms_method.physics.correlated_noise import blur_for_factor, correlated_noise, factor_of
from gaussian_atoms_method.physics.noise import noise_from_projections
from gaussian_atoms_method.physics.view_disagreement import view_disagreement

SIGMA_PX = 1.7
"""A Ta atom's width in the measured film's views (0.55 Å at 0.32 Å a pixel)."""


@pytest.mark.parametrize("factor", [3.0, 100.0, 5000.0])
def test_drawn_noise_shows_the_pixels_one_variance_and_an_atom_the_factor_asked_for(factor):
    """46 views of 96 x 96 px 2.6° apart: the pixels' reading is 1 within 5% (Immerkaer's filter
    over 4.4e5 pixels scatters by under 1%; the blur's discrete kernel is summed exactly), and the
    views' disagreement over an atom reads the factor within 10% (its MAD over 46 filtered views
    of 80 x 80 px, about 4% here)."""
    field = correlated_noise((46, 96, 96), factor, SIGMA_PX, np.random.default_rng(1))
    pixels = noise_from_projections(field)
    assert pixels.read_var == pytest.approx(1.0, rel=0.05) and pixels.gain == 0.0
    tilts = np.radians(np.linspace(-58.5, 58.5, 46))
    beams = np.c_[np.sin(tilts), np.zeros(46), np.cos(tilts)]
    read = view_disagreement(field, np.full(field.shape, pixels.read_var), SIGMA_PX, beams)
    assert read.noise_excess == pytest.approx(factor, rel=0.1)


def test_the_factor_grows_with_the_blur_from_one_for_white_noise():
    """White noise is 1 by construction; a wider blur hides more of the noise from neighbouring
    pixels than from an atom, so the factor rises with it and the blur found gives it back."""
    blurs = np.linspace(0.0, 2.0, 9)
    factors = [factor_of(b, SIGMA_PX) for b in blurs]
    assert factors[0] == pytest.approx(1.0) and np.all(np.diff(factors) > 0)
    assert blur_for_factor(1.0, SIGMA_PX) == 0.0
    assert factor_of(blur_for_factor(250.0, SIGMA_PX), SIGMA_PX) == pytest.approx(250.0, rel=1e-3)
