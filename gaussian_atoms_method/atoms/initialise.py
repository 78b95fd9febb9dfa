"""Where the Gaussians start: the candidates of a back-projection
(:mod:`.candidates`) or random positions, their starting masses, and the run's start (the
noise reading, the field of view and the positions, :func:`compute_start`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from gaussian_atoms_method.atoms.candidates import backprojection_candidates
from gaussian_atoms_method.physics.devices import default_device
from gaussian_atoms_method.physics.field_of_view import FieldOfView, field_of_view
from gaussian_atoms_method.physics.noise import NoiseModel
from gaussian_atoms_method.physics.reconstruction import Volume
from gaussian_atoms_method.physics.units import Normalisation


def starting_positions(
    series,
    length_scale: float,
    count: int,
    extent: float,
    generator: torch.Generator,
    from_backprojection: bool = True,
    noise: NoiseModel | None = None,
    slice_size_px: int | None = None,
    backprojection: Volume | None = None,
    positions_A: np.ndarray | None = None,
    device: str | None = None,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Where training starts: (n, 3) positions in normalised units and, for a back-projection
    start, (n,) weights of mean 1 in proportion to the smoothed back-projection there (else None).

    Parameters
    ----------
    series : TiltSeries or None
        The measured tilt series (``projections``, ``angles_deg``, ``pixel_size_A``,
        ``tilt_axis``, ``centre_px``); None, or ``from_backprojection`` False: a random start.
    length_scale : float
        Normalised length per Å (:class:`~gaussian_atoms_method.physics.units.Normalisation`).
    count : int
        The number of random positions (a back-projection start takes every candidate above
        the noise, :func:`backprojection_candidates`).
    extent : float
        Side of the cube (normalised units) the random positions fill.
    generator : torch.Generator
        Draws the random positions.
    noise : NoiseModel, optional
        The projections' noise in the series' units, if already read.
    slice_size_px : int, optional
        Across the tilt axis, start over this many voxels (:func:`backprojection_candidates`).
    backprojection : Volume, optional
        The candidates' back-projection if already made (:func:`backprojection_candidates`).
    positions_A : (n, 3) array, optional
        Start at these positions (Å), with equal masses, instead.
    device : str, optional
        Where the candidates are searched for (None: the GPU where torch sees one and the run is
        not asked for the CPU, :func:`~gaussian_atoms_method.physics.devices.default_device`).
    """
    if positions_A is not None:
        return torch.as_tensor(np.asarray(positions_A, dtype=np.float64) * length_scale, dtype=torch.float32), None
    if from_backprojection and series is not None:
        # A GPU, if there is one, does the back-projection (the model is built on the CPU).
        positions_A, values = backprojection_candidates(
            series.projections,
            series.angles_deg,
            series.pixel_size_A,
            series.tilt_axis,
            series.centre_px,
            None,
            device=default_device() if device is None else device,
            return_values=True,
            tilt_axis_angle_deg=series.tilt_axis_angle_deg,
            noise=noise,
            slice_size_px=slice_size_px,
            backprojection=backprojection,
        )
        if len(positions_A):
            # A candidate made of noise reads about zero; a floor of 1% of the strongest keeps
            # every weight positive (a log-amplitude) without making it atom-like.
            values = torch.as_tensor(values, dtype=torch.float64)
            values = values.clamp_min(0.01 * float(values.max().clamp_min(1e-30)))
            return torch.as_tensor(positions_A * length_scale, dtype=torch.float32), (values / values.mean()).float()
    return (torch.rand(count, 3, generator=generator) - 0.5) * extent, None


def starting_amplitude(
    projections, pixel_size_A: float | None, length_scale: float | None, n: int, sigma: float, data_range: float
) -> float:
    """3D peak (normalised units) that shares the measured mass equally among ``n`` Gaussians
    of width ``sigma`` (normalised): every Gaussian starts atom-like in total, and the fit sorts
    them.  ``projections``: (N, H, W) tensor in normalised data units.  Without data to size
    them by (any argument None): a faint 5% of a full-range projected peak."""
    if projections is None or pixel_size_A is None or length_scale is None:
        return 0.05 * data_range / (sigma * math.sqrt(2 * math.pi))
    pixel_area = (pixel_size_A * length_scale) ** 2
    mass = float(projections.double().sum(dim=(-2, -1)).mean().clamp_min(0.0)) * pixel_area
    mass_each = max(mass, 1e-12) / max(n, 1)
    return mass_each / (2 * math.pi * sigma**2) ** 1.5


EDGE_MARGIN_WIDTHS = 3.0
"""Along the tilt axis a film goes on past the detector: the volume reaches this many of the
widest atom's widths (``max_atom_sigma_A``) beyond it, where an atom still reaches the
detector's edge (99.7% of a Gaussian lies within three widths)."""


@dataclass
class Start:
    """What a run starts from: the measured noise of the normalised projections (None without
    data), the field of view, and the (n, 3) starting positions (normalised units) with their
    (n,) weights (None for a random start)."""

    noise: NoiseModel | None
    field: FieldOfView
    means: torch.Tensor
    weights: torch.Tensor | None


def compute_start(
    series,
    projections,
    normalisation: Normalisation,
    extended_object: str,
    max_atom_sigma_A: float,
    from_backprojection: bool = True,
    count: int = 0,
    extent: float = 1.0,
    generator: torch.Generator | None = None,
    *,
    noise: NoiseModel | None,
    backprojection: Volume | None = None,
    positions_A: np.ndarray | None = None,
    device: str | None = None,
) -> Start:
    """The start for a tilt series (``series``: :class:`~dataparsers.tilt_series_format.TiltSeries`,
    or None) with (V, H, W) ``projections`` in normalised data units: the noise measured once
    (the start and the data term share it), the field of view
    (:func:`~gaussian_atoms_method.physics.field_of_view.field_of_view`, ``extended_object`` its
    option) and the starting positions (:func:`~gaussian_atoms_method.atoms.initialise.starting_positions`:
    back-projection candidates, or ``count`` random ones in a cube of side ``extent`` drawn
    with ``generator``).  ``noise``: the projections' noise, read once by the caller
    (:func:`~gaussian_atoms_method.physics.noise.measure_noise`; None where none can be read);
    ``backprojection``: the candidates' back-projection if already made
    (:func:`~gaussian_atoms_method.physics.reconstruction.backprojection_for_peaks`
    of the series, across the tilt axis over the field's ``slice_px``); ``positions_A``: start at
    these atoms (Å) instead of any candidates; ``device``: where the candidates are searched for
    (None: :func:`~gaussian_atoms_method.physics.devices.default_device`)."""
    ls = normalisation.length_scale
    fov = field_of_view(series, projections, ls, extended_object, EDGE_MARGIN_WIDTHS * max_atom_sigma_A)
    generator = generator if generator is not None else torch.Generator()
    in_series_units = noise.scaled(1.0 / normalisation.data_scale) if noise is not None else None
    means, weights = starting_positions(
        series,
        ls,
        count,
        extent,
        generator,
        from_backprojection,
        in_series_units,
        fov.slice_px,
        backprojection,
        positions_A,
        device,
    )
    return Start(noise, fov, means, weights)
