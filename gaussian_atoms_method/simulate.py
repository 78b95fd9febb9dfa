"""Simulated tilt series with known atoms.

The quick forward model used here represents every atom's potential as an isotropic 3D
Gaussian (width ``atom_sigma_A``, integrated potential proportional to the atomic number),
projects it exactly, blurs the images with a Gaussian probe and adds Gaussian noise.  It is
the model our method assumes, so it serves demos and unit tests; independent-physics
potentials (abTEM, Lobato) belong to the accuracy harness.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage

from .atoms import AtomSet
from .geometry import detector_axes_from_tilts, pixel_centres
from .projector import project_gaussians

#: Integrated potential of one atom in the Gaussian model, per unit of atomic number
#: (arbitrary "projected potential" units x Å^2).  With a 0.35 Å atom and 0.5 Å blur one Au
#: atom peaks near 200 in a projection, the order of abTEM's projected potentials in V·Å.
MASS_PER_Z = 6.0

TILT_SCHEMES = {
    "full": "-90:1:90",
    "limited": "-70:3:68",
    "sampled": "-90:6:84",
    "wedge": "-70:1:70",
}


def parse_tilts(spec: str) -> np.ndarray:
    """Tilt angles in degrees from a scheme name or a MATLAB-style ``start:step:stop`` range.

    ``"full"`` = -90:1:90, ``"limited"`` = -70:3:68 (the paper's missing-wedge scheme),
    ``"sampled"`` = -90:6:84 (sparse, no wedge), ``"wedge"`` = -70:1:70; a comma-separated list
    of numbers is taken as it is.
    """
    spec = TILT_SCHEMES.get(spec, spec).strip()
    m = re.fullmatch(r"\s*(-?[\d.]+)\s*:\s*(-?[\d.]+)\s*:\s*(-?[\d.]+)\s*", spec)
    if m:
        start, step, stop = (float(g) for g in m.groups())
        if step == 0 or (stop - start) / step < 0:
            raise ValueError(f"tilt range {spec!r} is empty")
        n = int(np.floor((stop - start) / step + 1e-9)) + 1
        return start + step * np.arange(n)
    try:
        angles = np.array([float(a) for a in spec.split(",")])
    except ValueError:
        raise ValueError(
            f"tilts {spec!r}: expected one of {sorted(TILT_SCHEMES)}, 'start:step:stop' or a comma-separated list"
        ) from None
    return angles


def spherical_particle(element: str = "Au", radius_A: float = 10.0, lattice_constant_A: float | None = None) -> AtomSet:
    """An fcc sphere of ``element`` with its centre at the origin (built with ASE)."""
    from ase.build import bulk

    crystal = bulk(element, "fcc", a=lattice_constant_A, cubic=True)
    a = crystal.cell[0, 0]
    reps = int(np.ceil(2 * radius_A / a)) + 2
    crystal = crystal.repeat((reps, reps, reps))
    pos = crystal.get_positions()
    pos = pos - pos.mean(axis=0)
    # Centre on an atom so that the sphere is symmetric.
    pos = pos - pos[np.argmin(np.linalg.norm(pos, axis=1))]
    keep = np.linalg.norm(pos, axis=1) <= radius_A
    symbols = np.array(crystal.get_chemical_symbols())[keep]
    return AtomSet(pos[keep], species=symbols)


def gaussian_potential_parameters(species, atom_sigma_A: float = 0.35) -> tuple[np.ndarray, np.ndarray]:
    """Widths (Å) and 3D peak amplitudes of the quick Gaussian potential of each atom."""
    from ase.data import atomic_numbers

    z = np.array([atomic_numbers[s] for s in species], dtype=np.float64)
    mass = MASS_PER_Z * z
    sigmas = np.full(len(z), atom_sigma_A)
    amplitudes = mass / (2.0 * np.pi * sigmas**2) ** 1.5
    return sigmas, amplitudes


@dataclass
class SimulatedTiltSeries:
    projections: np.ndarray  # (N, H, W) float32
    angles_deg: np.ndarray  # (N,)
    pixel_size_A: float
    truth: AtomSet  # positions relative to the tilt centre, Å
    noise_std: float
    peak_to_noise: float


def simulate_gaussian_tilt_series(
    atoms: AtomSet,
    angles_deg: np.ndarray,
    pixel_size_A: float = 0.25,
    detector_pixels: int | None = None,
    margin_A: float = 4.0,
    atom_sigma_A: float = 0.35,
    blur_sigma_A: float = 0.5,
    noise_std: float = 20.0,
    tilt_axis: str = "y",
    seed: int = 0,
) -> SimulatedTiltSeries:
    """Project atoms (positions in Å about the tilt centre) with the Gaussian forward model.

    Parameters
    ----------
    atoms : AtomSet
        Positions relative to the tilt centre, Å; species set the amplitudes.
    angles_deg : (N,) array
    pixel_size_A : float
    detector_pixels : int, optional
        Side of the square detector; by default the particle's extent plus ``margin_A``.
    atom_sigma_A, blur_sigma_A : float
        Width of each atom's potential and of the Gaussian probe blur, Å.
    noise_std : float
        Standard deviation of the additive Gaussian noise, in projection units.
    tilt_axis : {"y", "x"}
    seed : int

    Returns
    -------
    SimulatedTiltSeries
    """
    if pixel_size_A <= 0:
        raise ValueError(f"pixel_size_A must be positive, got {pixel_size_A}")
    if detector_pixels is None:
        extent = 2 * (np.abs(atoms.positions).max() + margin_A)
        detector_pixels = int(np.ceil(extent / pixel_size_A))
    sigmas, amplitudes = gaussian_potential_parameters(atoms.species, atom_sigma_A)
    axes = torch.from_numpy(detector_axes_from_tilts(angles_deg, tilt_axis))
    coords = torch.from_numpy(pixel_centres(detector_pixels, pixel_size_A))
    means = torch.from_numpy(atoms.positions)
    images = []
    for start in range(0, len(axes), 8):  # a few views at a time bounds the memory
        images.append(
            project_gaussians(means, torch.from_numpy(sigmas), torch.from_numpy(amplitudes), axes[start : start + 8], coords, coords)
        )
    clean = torch.cat(images).numpy()
    if blur_sigma_A > 0:
        clean = ndimage.gaussian_filter(clean, sigma=(0, blur_sigma_A / pixel_size_A, blur_sigma_A / pixel_size_A), mode="constant")
    rng = np.random.default_rng(seed)
    noisy = clean + rng.normal(0.0, noise_std, size=clean.shape) if noise_std > 0 else clean
    truth = AtomSet(atoms.positions, sigmas=np.sqrt(sigmas**2 + blur_sigma_A**2), amplitudes=None, species=atoms.species)
    return SimulatedTiltSeries(
        projections=noisy.astype(np.float32),
        angles_deg=np.asarray(angles_deg, dtype=np.float64),
        pixel_size_A=float(pixel_size_A),
        truth=truth,
        noise_std=float(noise_std),
        peak_to_noise=float(clean.max() / noise_std) if noise_std > 0 else float("inf"),
    )
