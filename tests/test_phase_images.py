"""Ptychographic phase images through physics the fit does not share (physics/phase.py): each atom
its projected potential times the interaction constant, through the aperture's double overlap,
with the phase noise of a dose."""

import numpy as np
import pytest

from gaussian_atoms_method.physics.geometry import detector_axes_of
from gaussian_atoms_method.physics.microscope import ProbeOptics, electron_wavelength_A
from gaussian_atoms_method.physics.phase import (
    disc_overlap,
    phase_noise,
    phase_noise_std_rad,
    phase_weights,
    ptychographic_transfer,
)

PIXEL_A = 0.3


def test_a_phase_image_holds_each_atoms_integrated_phase_with_the_potentials_long_tails():
    """One C atom through the aperture's transfer: the view holds ``sigma * integral of V`` to
    1% (the transfer is 1 at zero frequency; the potential's tails beyond a 24 Å field hold
    less); it is non-negative (the double overlap is the transform of the aperture's Airy
    intensity); and it holds more of itself beyond 1 Å than the same atom's ADF image (a power
    1.7 of the potential) does, by more than a third: the phase is linear in the potential's tails."""
    from gaussian_atoms_method.physics.adf import adf_projections

    optics = ProbeOptics()
    weight = phase_weights(["C"], optics.voltage_kV)
    common = dict(probe=ptychographic_transfer(optics))
    axes, shape, centre = detector_axes_of([0.0]), (81, 81), (40.0, 40.0)
    phase = adf_projections(np.zeros((1, 3)), ["C"], weight, axes, shape, PIXEL_A, centre, power=1.0, **common)[0]
    adf = adf_projections(np.zeros((1, 3)), ["C"], weight, axes, shape, PIXEL_A, centre, **common)[0]
    assert phase.sum() * PIXEL_A**2 == pytest.approx(weight[0], rel=0.01)
    assert phase.argmax() == 40 * 81 + 40 and phase.min() > -1e-6 * phase.max()
    r = np.hypot(*np.meshgrid(np.arange(81) - 40.0, np.arange(81) - 40.0, indexing="ij")) * PIXEL_A
    beyond = [image[r > 1.0].sum() / image.sum() for image in (phase, adf)]
    assert beyond[0] > 1.33 * beyond[1]


def test_the_overlap_ends_at_twice_the_aperture_and_the_source_only_lowers_it():
    """The double overlap is 1 at zero frequency, falls monotonically, and is 0 from ``2 alpha /
    lambda`` on; a source of 0.7 Å lowers it everywhere but at zero frequency."""
    u = np.linspace(0.0, 1.2, 121)
    overlap = disc_overlap(u)
    assert overlap[0] == 1.0 and np.all(np.diff(overlap) <= 0) and np.all(overlap[u >= 1.0] == 0)
    shape, spacing = (64, 64), 0.1
    sharp = ptychographic_transfer(ProbeOptics())(shape, spacing)
    spread = ptychographic_transfer(ProbeOptics(source_fwhm_A=0.7))(shape, spacing)
    assert spread[0, 0] == sharp[0, 0] == 1.0
    assert np.all(spread <= sharp + 1e-15) and spread[0, 5] < sharp[0, 5]
    limit = 2 * ProbeOptics().semiangle_mrad * 1e-3 / electron_wavelength_A(300.0)
    q = np.hypot(*np.meshgrid(np.fft.fftfreq(64, spacing), np.fft.fftfreq(64, spacing), indexing="ij"))
    assert np.all(sharp[q >= limit] == 0) and np.all(sharp[q < 0.9 * limit] > 0)


def test_the_phase_noise_of_a_dose_has_its_variance_and_nothing_beyond_the_aperture():
    """Phase noise at 1e4 e/Å² on 0.3 Å pixels: per pixel its variance is the white variance
    ``1 / (2 N)`` times the overlap's mean over the grid's frequencies (Parseval), to 3% (1.5
    million draws: a variance's relative error 0.1%, 20 times over); its spectrum holds nothing
    beyond ``2 alpha / lambda``; neighbouring pixels are correlated (the band is narrower than
    the pixels' Nyquist frequency)."""
    optics = ProbeOptics()
    noise = phase_noise((40, 192, 192), 1e4, PIXEL_A, optics, np.random.default_rng(3))
    q = np.hypot(*np.meshgrid(np.fft.fftfreq(192, PIXEL_A), np.fft.fftfreq(192, PIXEL_A), indexing="ij"))
    u = q / (2 * optics.semiangle_mrad * 1e-3 / electron_wavelength_A(optics.voltage_kV))
    expected = phase_noise_std_rad(1e4, PIXEL_A) ** 2 * disc_overlap(u).mean()
    assert noise.var() == pytest.approx(expected, rel=0.03)
    power = (np.abs(np.fft.fft2(noise, axes=(1, 2))) ** 2).mean(0)
    assert power[u >= 1.0].max() < 1e-20 * power.max()
    neighbours = np.mean(noise[:, :, 1:] * noise[:, :, :-1]) / noise.var()
    assert neighbours > 0.1


def test_simulate_draws_phase_images_with_the_noise_of_their_dose():
    """``simulate_tilt_series(..., potential="phase", dose_e_per_A2=...)``: noiseless views hold
    every atom's integrated phase (to 2%: the tails beyond the margin); with a dose the drawn
    noise's standard deviation is returned; a dose with another contrast is refused."""
    from gaussian_atoms_method.atoms.atom_set import AtomSet
    from gaussian_atoms_method.harness.simulate import simulate_tilt_series

    atoms = AtomSet(np.array([[-2.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 0.0, 1.5]]), species=["C", "C", "O"])
    clean = simulate_tilt_series(atoms, np.array([-30.0, 0.0, 30.0]), potential="phase", noise_std=0.0,
                                 pixel_size_A=PIXEL_A, margin_A=8.0)  # fmt: skip
    total = phase_weights(atoms.species, 300.0).sum()
    np.testing.assert_allclose(clean.projections.sum(axis=(1, 2)) * PIXEL_A**2, total, rtol=0.02)
    noisy = simulate_tilt_series(atoms, np.array([-30.0, 0.0, 30.0]), potential="phase", pixel_size_A=PIXEL_A,
                                 margin_A=8.0, dose_e_per_A2=1e4)  # fmt: skip
    drawn = (noisy.projections - clean.projections).std()
    assert noisy.noise_std == pytest.approx(drawn, rel=1e-3)
    assert noisy.noise_std < phase_noise_std_rad(1e4, PIXEL_A)
    with pytest.raises(ValueError, match="phase"):
        simulate_tilt_series(atoms, np.array([0.0]), potential="adf", dose_e_per_A2=1e4)


def test_a_phase_series_says_so_and_a_contrast_that_is_neither_is_refused_naming_the_manifest(tmp_path):
    """`simulate --potential phase` writes ``"contrast": "phase"`` into the manifest and the
    series reads back as phase images (its own replica is then drawn through the aperture's
    transfer, engine/own_floor.py); a manifest's unknown contrast is refused in one line naming
    the manifest; an option overrides the manifest."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    from dataparsers.tilt_series_format import TiltSeriesError, load_tilt_series, update_manifest

    data = tmp_path / "phase"
    simulate = [str(Path(sys.executable).parent / "gaussian-atoms"), "simulate", "--output", str(data)]
    simulate += ["--particle", "sphere", "--element", "Au", "--radius-A", "4", "--potential", "phase"]
    simulate += ["--dose-e-per-A2", "1e4", "--tilts=-60:30:60", "--no-save-volume"]
    made = subprocess.run(simulate, capture_output=True, text=True, timeout=600)
    assert made.returncode == 0, made.stderr[-2000:]
    assert json.loads((data / "tilt_series.json").read_text())["contrast"] == "phase"
    assert load_tilt_series(data).contrast == "phase"
    assert load_tilt_series(data, contrast="adf").contrast == "adf"
    update_manifest(data, contrast="bright field")
    with pytest.raises(TiltSeriesError, match=r"tilt_series.json: contrast must be one of \['adf', 'phase'\]"):
        load_tilt_series(data)
