"""The views' own noise at the atoms' scale read from what neighbouring views do not share
(physics/view_disagreement.py): right where the spectrum cannot read it (denoised views), and
blind to a misfit of the object that every view sees."""

import numpy as np
import pytest
import torch
from scipy import ndimage

from gaussian_atoms_method.physics.geometry import detector_axes_from_tilts, pixel_centres
from gaussian_atoms_method.physics.noise import MAD_TO_STD, gaussian_taps, noise_from_projections
from gaussian_atoms_method.physics.noise_spectrum import noise_spectrum
from gaussian_atoms_method.physics.projector import project_gaussians
from gaussian_atoms_method.physics.view_disagreement import view_disagreement

SIGMA_PX = 1.7
"""A Ta atom's width in the measured film's views (0.55 Å at 0.32 Å a pixel)."""


def _series(blur_px: float, misfit: float, seed: int = 0):
    """46 views 2.6° apart, 96 x 96 px (1 Å a pixel): a misfit of the object that every view sees
    (80 Gaussian blobs of atomic width through the views' geometry, ``misfit`` times the noise's
    level over an atom) plus each view's own noise, white or blurred by ``blur_px`` (a denoised
    view's: its spectrum falls to the Nyquist frequency).  Returns the residuals, the noise drawn
    and the beams."""
    rng = np.random.default_rng(seed)
    tilts = np.linspace(-58.5, 58.5, 46)
    axes = detector_axes_from_tilts(tilts, "y")
    coords = torch.as_tensor(pixel_centres(96, 1.0))
    blobs = rng.uniform(-30, 30, (80, 3)) * np.array([1.0, 1.0, 0.4])
    shared = project_gaussians(
        torch.as_tensor(blobs),
        torch.full((80,), SIGMA_PX, dtype=torch.float64),
        torch.as_tensor(rng.choice([-1.0, 1.0], 80)),
        torch.as_tensor(axes),
        coords,
        coords,
    ).numpy()
    noise = rng.standard_normal((46, 96, 96))
    if blur_px:
        noise = ndimage.gaussian_filter(noise, (0, blur_px, blur_px), mode="wrap")
    over_atom = _over_atom(noise)
    shared *= misfit * np.sqrt(over_atom / _over_atom(shared))
    return shared + noise, noise, axes[:, 2]


def _over_atom(field: np.ndarray) -> float:
    """The robust variance of ``field`` filtered by the atom's Gaussian, per unit white noise."""
    radius = int(np.ceil(4 * SIGMA_PX))
    filtered = ndimage.gaussian_filter(field, (0, SIGMA_PX, SIGMA_PX), mode="constant", truncate=radius / SIGMA_PX)
    filtered = filtered[:, radius:-radius, radius:-radius]
    spread = MAD_TO_STD * np.median(np.abs(filtered - np.median(filtered)))
    return float(spread**2 / (gaussian_taps(SIGMA_PX, radius) ** 2).sum() ** 2)


@pytest.mark.parametrize("blur_px", [0.0, 1.1])
@pytest.mark.parametrize("misfit", [1.0, 3.0])
def test_the_noise_over_an_atom_is_read_within_20_percent_beside_a_misfit_every_view_sees(blur_px, misfit):
    """A misfit one or three times the noise over an atom, shared by the views through their
    geometry: the reading is the noise drawn within 20% (the misfit's change between neighbours is
    between the linear term the reading takes out and a quadratic one, which leaves it 16% low at
    the weaker misfit; the pairs' robust variances over about 10,000 pixels each scatter by 2-3%),
    the residual four to twelve times it."""
    residuals, noise, beams = _series(blur_px, misfit)
    pixel_variance = float(noise.var())
    read = view_disagreement(residuals, np.full(residuals.shape, pixel_variance), SIGMA_PX, beams)
    truth = _over_atom(noise / np.sqrt(pixel_variance))
    assert read.noise_excess == pytest.approx(truth, rel=0.2)
    assert read.residual_excess > 4 * truth and read.structure_share > 0.75


def test_denoised_views_hold_no_band_for_the_spectrum_but_their_disagreement_reads_the_noise():
    """Noise blurred by 1.1 px, as the measured Ta film's views fall: the spectrum finds no band
    beyond the atoms, and what neighbouring pixels show is a fraction of what an atom sees (the
    blur of 1.1 px keeps 1/15 of the pixel variance, all of it at zero frequency)."""
    residuals, noise, beams = _series(1.1, misfit=0.0)
    assert noise_spectrum(noise) is None or not noise_spectrum(noise).correlated
    read = view_disagreement(residuals, np.ones(residuals.shape), SIGMA_PX, beams)
    assert read.noise_excess == pytest.approx(_over_atom(noise), rel=0.2)
    assert read.noise_excess > 3 * float(noise.var())


def test_too_few_views_or_views_too_small_read_nothing():
    """Two views have no neighbours to compare at two separations; a view narrower than the
    atom's filter has no interior."""
    beams = np.c_[np.zeros(2), np.zeros(2), np.ones(2)]
    assert view_disagreement(np.zeros((2, 64, 64)), np.ones(1), 1.7, beams) is None
    assert view_disagreement(np.zeros((5, 12, 12)), np.ones(1), 1.7, np.tile([0.0, 0, 1], (5, 1))) is None


def test_a_run_on_denoised_views_states_its_residual_against_the_noise_neighbouring_views_do_not_share(capfd):
    """A 43-atom Au sphere in the model's own physics, its views' noise blurred by 1.1 px (as a
    denoiser leaves it): the spectrum holds no band, and the second differences of neighbouring
    pixels see little of the noise an atom sees.  The fit leaves the noise alone, so against the
    noise read from the views' disagreement its residual over an atom is about 1 (1.22 here, a
    quarter of its variance shared by the views: the fit is not the truth; bounded at 1.5 for that
    and the 15 views' 10° steps, whose pairs scatter by about 10%); stated against neighbouring
    pixels, as before this reading, it was 58.  The noise it reads over an atom is the noise drawn within
    20%, as on the constructed stacks above."""
    import re

    import gaussian_atoms_method as ga
    from gaussian_atoms_method.harness.simulate import simulate_tilt_series, spherical_particle

    truth = spherical_particle("Au", radius_A=5.0)
    angles = np.arange(-70.0, 71.0, 10.0)
    clean = simulate_tilt_series(truth, angles, potential="gaussian", noise_std=0.0, seed=0).projections
    noise = ndimage.gaussian_filter(np.random.default_rng(1).standard_normal(clean.shape), (0, 1.1, 1.1))
    projections = clean + 40.0 * noise / noise.std() / np.sqrt(4 * np.pi * 1.1**2)
    ga.reconstruct(projections, angles, 0.25, device="cpu", max_num_iterations=400, progress=False)
    said = re.sub(r"\s+", " ", capfd.readouterr().out)  # the console wraps its lines
    assert "the spectrum holds no band" in said or "read from neighbouring pixels only" in said
    read = re.search(r"do not share of the fit's residual: ([0-9.e+]+) times the variance neighbouring pixels", said)
    drawn = projections - clean  # the noise over an atom of the noise drawn, in the pre-fit reading's units
    before = noise_from_projections(projections).variance(np.clip(clean, 0, None))
    assert float(read[1]) == pytest.approx(_over_atom(drawn / np.sqrt(before)), rel=0.2)
    ratio = float(re.search(r"over an atom ([0-9.]+) times the noise the views hold there \(read from what", said)[1])
    assert 0.8 < ratio < 1.5
