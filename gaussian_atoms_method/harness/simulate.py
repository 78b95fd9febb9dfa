"""Simulated tilt series with known atoms.

The potentials:

* ``lobato`` (the accuracy harness): abTEM's projected potentials with the Lobato
  parametrisation, computed for the atoms rotated to each tilt.  Independent physics: sharp
  cores and long tails, nothing like our Gaussians, so fitting it is no inverse crime.
  Needs the optional extra ``gaussian-atoms[sim]`` (abTEM).
* ``adf`` and ``phase``: ADF views (a power of each atom's Lobato projected potential, ``Z^1.7``
  contrast, the probe from its optics, :mod:`~gaussian_atoms_method.physics.adf`) and
  ptychographic phase images (the projected potential through the aperture's transfer, rad, the
  phase noise of a dose, :mod:`~gaussian_atoms_method.physics.phase`), drawn without abTEM.
* ``gaussian`` (demos and unit tests): every atom an isotropic 3D Gaussian (width
  ``atom_sigma_A``, integrated potential proportional to the atomic number), projected exactly.

``lobato`` and ``gaussian`` are then blurred by a probe; all get additive Gaussian noise of a
stated standard deviation, in projection units (V·Å for Lobato), or a phase image the noise of its dose.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage

from gaussian_atoms_method.atoms.atom_set import AtomSet
from gaussian_atoms_method.physics.geometry import detector_axes_of, pixel_centres
from gaussian_atoms_method.physics.projector import project_gaussians

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


def _detector_size(atoms: AtomSet, pixel_size_A: float, margin_A: float) -> int:
    extent = 2 * (np.abs(atoms.positions).max() + margin_A)
    return int(np.ceil(extent / pixel_size_A))


def project_gaussian_potential(
    atoms: AtomSet,
    angles_deg,
    pixel_size_A: float,
    detector_pixels: int,
    atom_sigma_A: float = 0.35,
    tilt_axis: str = "y",
) -> np.ndarray:
    """Exact projections ``(N, P, P)`` of the quick Gaussian potential (positions about the tilt centre)."""
    sigmas, amplitudes = gaussian_potential_parameters(atoms.species, atom_sigma_A)
    axes = torch.from_numpy(detector_axes_of(angles_deg, tilt_axis))
    coords = torch.from_numpy(pixel_centres(detector_pixels, pixel_size_A))
    means = torch.from_numpy(atoms.positions)
    images = []
    for start in range(0, len(axes), 8):  # a few views at a time bounds the memory
        images.append(
            project_gaussians(
                means, torch.from_numpy(sigmas), torch.from_numpy(amplitudes), axes[start : start + 8], coords, coords
            )
        )
    return torch.cat(images).numpy()


def project_lobato_potential(
    atoms: AtomSet, angles_deg, pixel_size_A: float, detector_pixels: int, tilt_axis: str = "y"
) -> np.ndarray:
    """abTEM projected potentials ``(N, P, P)`` in V·Å with the Lobato parametrisation.

    For each tilt the atoms (positions in Å about the tilt centre) are rotated into detector
    coordinates and abTEM integrates their potential along the beam (``projection="infinite"``).
    abTEM samples grid point ``i`` at ``i * sampling``, so the tilt centre is placed at
    ``(P - 1) / 2 * pixel_size`` to match our pixel convention.  abTEM's potential is periodic
    in the detector plane: keep a margin of a few Å around the particle.
    """
    try:
        import abtem
        import ase
    except ImportError as exc:  # pragma: no cover - depends on the optional extra
        raise ImportError("the Lobato potential needs abTEM: pip install 'gaussian-atoms[sim]'") from exc
    abtem.config.set({"device": "cpu", "progress_bar": False})
    side = detector_pixels * pixel_size_A
    centre = (detector_pixels - 1) / 2 * pixel_size_A
    axes = detector_axes_of(angles_deg, tilt_axis)
    depth = 2 * np.abs(atoms.positions).max() + 10.0
    out = np.empty((len(axes), detector_pixels, detector_pixels), dtype=np.float64)
    symbols = list(atoms.species)
    for k, d in enumerate(axes):
        local = atoms.positions @ d.T  # (row, column, depth) coordinates
        local = local + [centre, centre, depth / 2]
        cell = ase.Atoms(symbols, positions=local, cell=[side, side, depth], pbc=True)
        potential = abtem.Potential(
            cell,
            gpts=(detector_pixels, detector_pixels),
            parametrization="lobato",
            projection="infinite",
            slice_thickness=depth,
        )
        out[k] = potential.build().compute(progress_bar=False).array.sum(axis=0)
    return out


def lobato_potential_volume(atoms: AtomSet, voxel_size_A: float, voxels: int, blur_sigma_A: float = 0.5) -> np.ndarray:
    """The true 3D potential (V) on a cube of ``voxels``^3, blurred like the data, for SSIM.

    Voxel ``(i, j, k)`` is centred at ``((i, j, k) - (voxels - 1) / 2) * voxel_size_A`` about the
    tilt centre (the convention of the projections).  abTEM integrates the Lobato potential
    over slices one voxel thick (``projection="finite"``); dividing by the thickness gives the
    mean potential of each voxel-thick slab, sampled at the voxel centres in x and y.  Then a
    3D Gaussian blur of ``blur_sigma_A``: the probe blur the projections received.
    """
    import abtem
    import ase

    abtem.config.set({"device": "cpu", "progress_bar": False})
    side = voxels * voxel_size_A
    # x, y: abTEM samples grid point i at i * size; z: slab k spans [k, k + 1) * size.
    shift = np.array([(voxels - 1) / 2, (voxels - 1) / 2, voxels / 2]) * voxel_size_A
    cell = ase.Atoms(list(atoms.species), positions=atoms.positions + shift, cell=[side] * 3, pbc=True)
    potential = abtem.Potential(
        cell, gpts=(voxels, voxels), slice_thickness=voxel_size_A, parametrization="lobato", projection="finite"
    )
    slabs = potential.build().compute(progress_bar=False).array  # (z, x, y) in V·Å
    volume = np.moveaxis(slabs, 0, -1).astype(np.float64) / voxel_size_A
    if blur_sigma_A > 0:
        volume = ndimage.gaussian_filter(volume, blur_sigma_A / voxel_size_A, mode="constant")
    return volume.astype(np.float32)


def blur_and_noise(
    clean: np.ndarray, pixel_size_A: float, blur_sigma_A: float, noise_std: float, seed: int
) -> np.ndarray:
    """Gaussian probe blur of each projection, then additive Gaussian noise (float64)."""
    if blur_sigma_A > 0:
        clean = ndimage.gaussian_filter(
            clean, sigma=(0, blur_sigma_A / pixel_size_A, blur_sigma_A / pixel_size_A), mode="constant"
        )
    if noise_std > 0:
        clean = clean + np.random.default_rng(seed).normal(0.0, noise_std, size=clean.shape)
    return clean


@dataclass
class SimulatedTiltSeries:
    projections: np.ndarray  # (N, H, W) float32
    angles_deg: np.ndarray  # (N,)
    pixel_size_A: float
    truth: AtomSet  # positions relative to the tilt centre, Å
    noise_std: float
    peak_to_noise: float


def simulate_tilt_series(
    atoms: AtomSet,
    angles_deg: np.ndarray,
    potential: str = "lobato",
    pixel_size_A: float = 0.25,
    detector_pixels: int | None = None,
    margin_A: float = 4.0,
    atom_sigma_A: float = 0.35,
    blur_sigma_A: float = 0.5,
    noise_std: float = 50.0,
    tilt_axis: str = "y",
    seed: int = 0,
    probe: str = "gaussian",
    floor_fraction: float = 0.0,
    floor_variation: float = 0.0,
    field_of_view_A: float | None = None,
    optics=None,
    dose_e_per_A2: float | None = None,
) -> SimulatedTiltSeries:
    """Project atoms (positions in Å about the tilt centre), blur, add a floor, add noise.

    Parameters
    ----------
    atoms : AtomSet
        Positions relative to the tilt centre, Å, with species.
    angles_deg : (N,) array
    potential : {"lobato", "adf", "phase", "gaussian"}
        abTEM's Lobato projected potential; ADF views (each atom a power of its Lobato projected
        potential with ADF-STEM's ``Z^1.7`` contrast, :mod:`.adf`, the probe drawn with the atoms:
        physics the fit does not share); ptychographic phase images (rad: each atom its projected
        potential times the interaction constant, through the aperture's double overlap and the
        source, :mod:`.phase`; ``probe`` and ``blur_sigma_A`` unused); or the quick Gaussian model.
    pixel_size_A : float
    detector_pixels : int, optional
        Side of the square detector; by default the particle's extent plus ``margin_A``.
    atom_sigma_A : float
        Width of each atom of the Gaussian potential, Å (``potential="gaussian"`` only).
    blur_sigma_A : float
        Gaussian probe blur, Å.
    noise_std : float
        Standard deviation of the additive Gaussian noise, in projection units.
    tilt_axis : {"y", "x"}
    seed : int
    probe : {"gaussian", "aberrated"}
        The blur: a Gaussian of ``blur_sigma_A``, or an aberrated probe's intensity with rings
        and tails (:class:`.microscope.ProbeOptics`; ``blur_sigma_A`` unused).
    floor_fraction, floor_variation : float
        A floor under every view at this fraction of a column's value, varying across the view
        by this fraction (:func:`.microscope.add_varying_floor`); 0: none.
    field_of_view_A : float, optional
        A detector narrower than the object (a film): the views are projected through all of it,
        blurred, then cropped to this side about the tilt centre; the truth holds the atoms
        above the detector (both in-plane coordinates within half the side).

    optics : ProbeOptics, optional
        The aberrated probe's optics (default: :class:`.microscope.ProbeOptics`' defaults).
    dose_e_per_A2 : float, optional
        ``potential="phase"`` only: the noise is the phase noise of this dose per view
        (:func:`.phase.phase_noise`) instead of ``noise_std``; ``noise_std`` is then returned as
        its standard deviation per pixel.

    Returns
    -------
    SimulatedTiltSeries
        ``peak_to_noise`` is the largest clean (blurred) projection value over ``noise_std``.
    """
    if pixel_size_A <= 0:
        raise ValueError(f"pixel_size_A must be positive, got {pixel_size_A}")
    if atoms.species is None:
        raise ValueError("atoms need species to simulate their potential")
    if detector_pixels is None:
        detector_pixels = _detector_size(atoms, pixel_size_A, margin_A)
    if potential == "gaussian":
        clean = project_gaussian_potential(atoms, angles_deg, pixel_size_A, detector_pixels, atom_sigma_A, tilt_axis)
        widths = np.full(len(atoms), np.hypot(atom_sigma_A, blur_sigma_A))
    elif potential == "lobato":
        clean = project_lobato_potential(atoms, angles_deg, pixel_size_A, detector_pixels, tilt_axis)
        widths = None
    elif potential in ("adf", "phase"):
        clean = _adf_views(
            atoms, angles_deg, pixel_size_A, detector_pixels, tilt_axis, probe, blur_sigma_A, optics, potential
        )
        widths = None
    else:
        raise ValueError(f"potential must be 'lobato', 'adf', 'phase' or 'gaussian', got {potential!r}")
    if dose_e_per_A2 is not None and potential != "phase":
        raise ValueError("a dose draws the phase noise of a phase image: give potential='phase', or noise_std")
    if potential in ("adf", "phase"):
        blurred = clean  # the probe is drawn with the atoms
    elif probe == "aberrated":
        from gaussian_atoms_method.physics.microscope import ProbeOptics, convolve_views

        blurred, widths = convolve_views(clean, (optics or ProbeOptics()).intensity(pixel_size_A)), None
    elif probe == "gaussian":
        blurred = blur_and_noise(clean, pixel_size_A, blur_sigma_A, 0.0, seed)
    else:
        raise ValueError(f"probe must be 'gaussian' or 'aberrated', got {probe!r}")
    if field_of_view_A is not None:
        blurred, atoms, widths = _crop_to_field(blurred, atoms, widths, pixel_size_A, field_of_view_A)
    if floor_fraction:
        from gaussian_atoms_method.physics.microscope import add_varying_floor

        blurred = add_varying_floor(blurred, floor_fraction, floor_variation, seed)
    if dose_e_per_A2 is not None:
        from gaussian_atoms_method.physics.microscope import ProbeOptics
        from gaussian_atoms_method.physics.phase import phase_noise

        drawn = phase_noise(
            blurred.shape, dose_e_per_A2, pixel_size_A, optics or ProbeOptics(), np.random.default_rng(seed)
        )
        noisy, noise_std = blurred + drawn, float(drawn.std())
    else:
        noisy = blur_and_noise(blurred, pixel_size_A, 0.0, noise_std, seed)
    return SimulatedTiltSeries(
        projections=noisy.astype(np.float32),
        angles_deg=np.asarray(angles_deg, dtype=np.float64),
        pixel_size_A=float(pixel_size_A),
        truth=AtomSet(atoms.positions, sigmas=widths, species=atoms.species),
        noise_std=float(noise_std),
        peak_to_noise=float(blurred.max() / noise_std) if noise_std > 0 else float("inf"),
    )


def _adf_views(atoms, angles_deg, pixel_size_A, detector_pixels, tilt_axis, probe, blur_sigma_A, optics, contrast):
    """ADF views (:func:`.adf.adf_projections`: each atom a power of its Lobato projected potential
    with intensity ``Z^1.7``) through the probe, or phase images (``contrast="phase"``: each atom
    its projected potential, :mod:`.phase`), on a square detector centred on the tilt centre."""
    from gaussian_atoms_method.physics.adf import ADF_POTENTIAL_POWER, adf_projections, adf_weights
    from gaussian_atoms_method.physics.microscope import ProbeOptics, probe_transfer
    from gaussian_atoms_method.physics.phase import phase_weights, ptychographic_transfer

    optics = optics or ProbeOptics()
    if contrast == "phase":
        transfer, weights, power = ptychographic_transfer(optics), phase_weights(atoms.species, optics.voltage_kV), 1.0
    else:
        transfer, weights, power = (
            probe_transfer(probe, optics, blur_sigma_A),
            adf_weights(atoms.species),
            ADF_POTENTIAL_POWER,
        )
    centre = (detector_pixels - 1) / 2.0
    axes = detector_axes_of(angles_deg, tilt_axis)
    shape = (detector_pixels, detector_pixels)
    return adf_projections(
        atoms.positions, atoms.species, weights, axes, shape, pixel_size_A, (centre, centre), probe=transfer,
        power=power,
    )  # fmt: skip


def _crop_to_field(views: np.ndarray, atoms: AtomSet, widths, pixel_size_A: float, field_of_view_A: float):
    """The central ``field_of_view_A`` of (N, P, P) ``views`` (the side rounded to pixels of the
    same parity as P, so the pixel centres stay where they were) and the atoms above it."""
    size = views.shape[-1]
    field = min(int(round(field_of_view_A / pixel_size_A)), size)
    field -= (size - field) % 2
    start = (size - field) // 2
    inside = np.all(np.abs(atoms.positions[:, :2]) <= 0.5 * field * pixel_size_A, axis=1)
    kept = AtomSet(atoms.positions[inside], species=atoms.species[inside])
    return views[:, start : start + field, start : start + field], kept, (None if widths is None else widths[inside])


def simulate_gaussian_tilt_series(atoms: AtomSet, angles_deg: np.ndarray, **kwargs) -> SimulatedTiltSeries:
    """:func:`simulate_tilt_series` with the quick Gaussian potential (demo default noise 20)."""
    kwargs.setdefault("noise_std", 20.0)
    return simulate_tilt_series(atoms, angles_deg, potential="gaussian", **kwargs)


def true_potential_volume(
    truth: AtomSet,
    potential: str,
    voxel_size_A: float,
    voxels: int,
    atom_sigma_A: float = 0.35,
    blur_sigma_A: float = 0.5,
) -> np.ndarray:
    """The true potential on a ``voxels``^3 grid about the tilt centre, blurred like the data (float32)."""
    from gaussian_atoms_method.harness.metrics import voxelise_gaussians

    if potential in ("lobato", "phase"):  # a phase image is the potential times a constant
        return lobato_potential_volume(truth, voxel_size_A, voxels, blur_sigma_A)
    # Gaussian model: blurring a Gaussian atom gives a Gaussian of the combined width and mass.
    sigmas, amplitudes = gaussian_potential_parameters(truth.species, atom_sigma_A)
    wide = np.hypot(sigmas, blur_sigma_A)
    amplitudes = amplitudes * (sigmas / wide) ** 3
    return voxelise_gaussians(truth.positions, wide, amplitudes, voxel_size_A, (voxels,) * 3).astype(np.float32)
