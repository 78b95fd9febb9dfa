"""The replica's probe (physics/probe_width.py): the source that makes one atom as wide as the fit
reads it, solved back from the width it gives."""

import dataclasses

import numpy as np
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


@pytest.mark.parametrize("contrast", ["adf", "phase"])
@pytest.mark.parametrize("source_fwhm_A", [0.5, 1.0])
def test_the_source_is_read_from_views_against_the_atoms_drawn_with_none(contrast, source_fwhm_A):
    """40 Pd atoms drawn through Lobato's potentials, the default optics and a source, in ADF or
    phase contrast, with white noise at a tenth of the views' peak: the cross-spectrum against
    the same atoms drawn with no source reads the source within 0.05 Å (a tenth of the narrower
    one; the noise is independent of the atoms and averages out over 13 views' rings)."""
    from gaussian_atoms_method.physics.adf import adf_projections
    from gaussian_atoms_method.physics.geometry import detector_axes_of
    from gaussian_atoms_method.physics.probe_width import contrast_transfer, source_read_from_views

    rng = np.random.default_rng(11)
    positions = rng.uniform(-6.0, 6.0, (40, 3))
    axes, shape, pixel = detector_axes_of(np.linspace(-60, 60, 13)), (64, 64), 0.35

    def drawn(fwhm):
        transfer, power = contrast_transfer(dataclasses.replace(DEFAULT_OPTICS, source_fwhm_A=fwhm), contrast)
        return adf_projections(positions, ["Pd"] * 40, np.ones(40), axes, shape, pixel, (31.5, 31.5),
                               probe=transfer, power=power)  # fmt: skip

    views = drawn(source_fwhm_A)
    measured = views + rng.normal(0.0, 0.1 * views.max(), views.shape)
    assert source_read_from_views(measured, drawn(0.0), pixel) == pytest.approx(source_fwhm_A, abs=0.05)


@pytest.mark.parametrize(
    "truth",
    [
        dataclasses.replace(DEFAULT_OPTICS, source_fwhm_A=0.7),  # rings: 40 Å of defocus, Cs 10 µm
        dataclasses.replace(DEFAULT_OPTICS, defocus_A=0.0, cs_A=0.0, source_fwhm_A=1.0),  # a corrected probe
    ],
)
def test_an_adf_replicas_probe_is_read_among_its_candidates_with_its_source(truth):
    """40 Pd atoms through ADF contrast, a probe of the replica's candidates and a source, white
    noise at a tenth of the views' peak: the probe read draws them as the truth does, its transfer
    within 0.02 of the truth's (1 at zero frequency) at every frequency of the detector (the two
    truths here differ by up to 0.17), with
    a source within 0.1 Å: a corrected probe behind a 1 Å source is read as Cs balanced by
    defocus behind a 0.93 Å one, the same transfer within 0.013.  The atoms it is read against
    are drawn through no probe, as the run draws them
    (:func:`~gaussian_atoms_method.engine.own_floor.drawn_atoms`)."""
    from gaussian_atoms_method.engine.own_floor import PROBE_CANDIDATES
    from gaussian_atoms_method.physics.adf import adf_projections
    from gaussian_atoms_method.physics.geometry import detector_axes_of
    from gaussian_atoms_method.physics.microscope import band_limit
    from gaussian_atoms_method.physics.probe_width import probe_read_from_views

    rng = np.random.default_rng(12)
    positions = rng.uniform(-6.0, 6.0, (40, 3))
    axes, shape, pixel = detector_axes_of(np.linspace(-60, 60, 13)), (64, 64), 0.35

    def drawn(probe):
        return adf_projections(positions, ["Pd"] * 40, np.ones(40), axes, shape, pixel, (31.5, 31.5), probe=probe)

    views = drawn(truth.transfer)
    measured = views + rng.normal(0.0, 0.1 * views.max(), views.shape)
    read = probe_read_from_views(measured, drawn(band_limit(pixel)), pixel, PROBE_CANDIDATES)
    assert np.abs(read.transfer(shape, pixel) - truth.transfer(shape, pixel)).max() < 0.02
    assert read.source_fwhm_A == pytest.approx(truth.source_fwhm_A, abs=0.1)
