"""Ptychographic phase images through physics the fit does not share: the object's phase, the
transfer of the probe's aperture, and the phase noise of a dose.

A phase image (electron ptychography) measures the phase the specimen gives the beam, ``sigma
V_p(r)`` with ``V_p`` the projected potential and ``sigma`` the interaction constant
(:func:`interaction_constant_rad_per_VA`).  Each atom's image is then its element's projected
potential itself (Lobato's: a core that diverges as ``-log r`` and long tails), carrying the
integrated phase ``sigma * integral of V_p`` (:func:`phase_weights`), linear in the potential, not
in a power of it as ADF contrast is (:mod:`.adf`).

The reconstruction solves for the probe, so its aberrations leave the phase; what stays is what
the aperture lets through.  A beam scattered by spatial frequency ``q`` interferes with the
unscattered one only where the bright-field disc and its copy shifted by ``q`` overlap, so the
phase is transferred in proportion to that double overlap (:func:`ptychographic_transfer`: the
discs' overlap fraction, 1 at ``q = 0`` and 0 at ``2 alpha / lambda``), times the effective
source's partial coherence.  The noise of a dose follows the same overlap: a frequency is
measured by as many electrons as fall in its overlap (:func:`phase_noise`).

Pure numpy; used by :func:`~gaussian_atoms_method.harness.simulate.simulate_tilt_series`
(``potential="phase"``).
"""

from __future__ import annotations

import numpy as np

from gaussian_atoms_method.physics.microscope import electron_wavelength_A, gaussian_transfer

ELECTRON_REST_ENERGY_KEV = 510.99895
"""The electron's rest energy, keV (CODATA 2018)."""


def interaction_constant_rad_per_VA(voltage_kV: float) -> float:
    """The phase a projected potential of 1 V·Å gives the beam, rad (relativistic):
    ``sigma = 2 pi / (lambda V) (m0 c^2 + e V) / (2 m0 c^2 + e V)`` (Kirkland, Advanced Computing
    in Electron Microscopy, eq. 5.6).

    >>> round(interaction_constant_rad_per_VA(300.0) * 1e4, 3)
    6.526
    """
    wavelength = electron_wavelength_A(voltage_kV)
    rest = ELECTRON_REST_ENERGY_KEV
    return float(2 * np.pi / (wavelength * voltage_kV * 1e3) * (rest + voltage_kV) / (2 * rest + voltage_kV))


def integrated_potential_VA3(element: str) -> float:
    """``element``'s projected potential integrated over the plane, V·Å³: its electron scattering
    factor at zero angle over kappa, ``f(0) / kappa = 2 sum_i a_i / kappa`` (Lobato's parameters,
    :mod:`.lobato`; the numerical integral of its projected potential agrees to 1e-6).

    >>> carbon, tantalum = integrated_potential_VA3("C"), integrated_potential_VA3("Ta")
    >>> round(carbon, 1), round(carbon / tantalum, 3)
    (120.2, 0.194)
    """
    from gaussian_atoms_method.physics.lobato import KAPPA, lobato_parameters

    a, _ = lobato_parameters(element)
    return float(2.0 * a.sum() / KAPPA)


def phase_weights(species, voltage_kV: float) -> np.ndarray:
    """(N,) each atom's integrated phase, rad·Å²: its element's integrated projected potential
    (:func:`integrated_potential_VA3`) times the interaction constant at ``voltage_kV``."""
    sigma = interaction_constant_rad_per_VA(voltage_kV)
    per_element = {e: sigma * integrated_potential_VA3(e) for e in set(np.asarray(species).tolist())}
    return np.array([per_element[s] for s in np.asarray(species).tolist()], dtype=np.float64)


def disc_overlap(q_over_2k: np.ndarray) -> np.ndarray:
    """The overlap of two unit discs whose centres lie ``2 u`` radii apart, as a fraction of one
    disc's area: ``(2 / pi) (acos u - u sqrt(1 - u^2))`` for ``u <= 1``, else 0.

    >>> disc_overlap(np.array([0.0, 1.0, 2.0])).tolist()
    [1.0, 0.0, 0.0]
    """
    u = np.clip(np.abs(np.asarray(q_over_2k, dtype=np.float64)), 0.0, 1.0)
    return (2.0 / np.pi) * (np.arccos(u) - u * np.sqrt(1.0 - u * u))


def _aperture_frequency(optics) -> float:
    """The bright-field disc's radius in spatial frequency, ``alpha / lambda`` (1/Å)."""
    return optics.semiangle_mrad * 1e-3 / electron_wavelength_A(optics.voltage_kV)


def _overlap_on_grid(shape: tuple[int, int], spacing_A: float, optics) -> np.ndarray:
    """The double overlap (:func:`disc_overlap`) at each frequency of a periodic grid (FFT order)."""
    q = np.hypot(np.fft.fftfreq(shape[0], d=spacing_A)[:, None], np.fft.fftfreq(shape[1], d=spacing_A)[None, :])
    return disc_overlap(q / (2.0 * _aperture_frequency(optics)))


def ptychographic_transfer(optics):
    """``transfer(shape, spacing_A)``: what multiplies a phase image's spectrum on a periodic grid
    (numpy's FFT order, 1 at zero frequency): the double overlap of the probe's bright-field disc
    (radius ``semiangle / wavelength`` of ``optics``, a
    :class:`~gaussian_atoms_method.physics.microscope.ProbeOptics`) times the effective source's
    Gaussian transfer (``source_fwhm_A``).  Defocus and Cs do not enter: the reconstruction
    solves for the probe.

    >>> from gaussian_atoms_method.physics.microscope import ProbeOptics
    >>> t = ptychographic_transfer(ProbeOptics())((64, 64), 0.1)
    >>> float(t[0, 0]), bool(t[0, 25] == 0.0)  # 2.5 / Å lies beyond 2 alpha / lambda = 2.03 / Å
    (1.0, True)
    """

    def transfer(shape: tuple[int, int], spacing_A: float) -> np.ndarray:
        out = _overlap_on_grid(shape, spacing_A, optics)
        if optics.source_fwhm_A > 0:
            out = out * gaussian_transfer(optics.source_fwhm_A / (2.0 * np.sqrt(2.0 * np.log(2.0))), shape, spacing_A)
        return out

    return transfer


def phase_noise_std_rad(dose_e_per_A2: float, pixel_size_A: float) -> float:
    """The phase noise of one pixel's electrons, white, rad: ``1 / sqrt(2 N)`` with ``N`` the
    electrons on the pixel, twice the variance of the quantum limit ``1 / (4 N)`` (a phase read by
    interference with an equal reference), as a ptychographic reconstruction of Poisson counts
    comes within a factor of about 2 of it.

    >>> round(phase_noise_std_rad(1e4, 0.5), 4)
    0.0141
    """
    if dose_e_per_A2 <= 0:
        raise ValueError(f"the dose must be positive, got {dose_e_per_A2} e/Å²")
    return float(1.0 / np.sqrt(2.0 * dose_e_per_A2 * pixel_size_A**2))


def phase_noise(
    shape: tuple[int, int, int], dose_e_per_A2: float, pixel_size_A: float, optics, rng: np.random.Generator
) -> np.ndarray:
    """(V, H, W) phase noise of ``dose_e_per_A2`` per view: white noise of
    :func:`phase_noise_std_rad` whose spectrum is shaped by the square root of the double overlap
    (a frequency is measured by the electrons in its overlap, and the reconstruction returns it in
    proportion to them, so its noise power follows the overlap), hence correlated between
    neighbouring pixels, with nothing beyond ``2 alpha / lambda``."""
    white = rng.normal(0.0, phase_noise_std_rad(dose_e_per_A2, pixel_size_A), size=shape)
    shaping = np.sqrt(_overlap_on_grid(shape[1:], pixel_size_A, optics))
    return np.fft.ifft2(np.fft.fft2(white, axes=(1, 2)) * shaping[None], axes=(1, 2)).real
