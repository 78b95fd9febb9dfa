"""Objects wider than the field of view: a film, a crowded support, a particle cut by the frame.

A parallel-beam view at tilt ``theta`` of an object that lies wholly inside the field of view
holds all of its mass at every tilt: the projected mass per view is constant.  A slab wider
than the detector puts more material under the detector as it tilts, in proportion to the path
length ``t / cos(theta)``: its projected mass per view grows like ``1 / cos(theta)``, and at
high tilt the rays reaching the detector cross material outside the box above it.  A model that
holds Gaussians only inside that box must explain those rays with false atoms inside it.

:func:`film_evidence` reads the sign from the data: the least-squares fit of the views' mass
``M(theta) = a + b / |cos(theta)|``, written ``M |cos| = a |cos| + b`` so that no view near
90 degrees (a full tilt range) dominates the fit, and ``b``'s significance against the scatter of
the views about it (alignment, beam current and noise all enter the scatter, so the test needs
no noise model).  :func:`slab_half_width` gives how far across the tilt axis the rays that reach the
detector travel through a slab of a given half-thickness: the box the Gaussians must fill.
Torch-free numpy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from gaussian_atoms_method.physics.noise import as_array

FILM_Z = 3.0
"""``b`` (the mass growing like 1/cos theta) counts when it is this many standard errors above
zero: a one-in-700 false alarm for Gaussian scatter.  The four Ta film sub-areas read 5.5-24;
particles inside the field of view (the demo's Au sphere, the aSi-208 counts at all three doses,
whose 0-177 degree tilts pass 90) read within 0.5 standard errors of zero."""


@dataclass(frozen=True)
class FilmEvidence:
    """The fit ``M(theta) = constant + growing / cos(theta)`` of the views' projected mass."""

    constant: float
    growing: float
    growing_se: float

    @property
    def z(self) -> float:
        """``growing`` in standard errors (infinite for an exact fit with growth)."""
        if self.growing_se > 0:
            return self.growing / self.growing_se
        return math.inf if self.growing > 0 else 0.0

    @property
    def extended(self) -> bool:
        """Material beyond the field of view enters the views as they tilt (``z`` > :data:`FILM_Z`)."""
        return self.z > FILM_Z

    @property
    def outside_fraction(self) -> float:
        """The share of the zero-tilt view's mass that grows like ``1 / cos(theta)``."""
        total = self.constant + self.growing
        return self.growing / total if total > 0 else 0.0


def film_evidence(projections: np.ndarray, angles_deg: np.ndarray, floor: float = 0.0) -> FilmEvidence:
    """Fit the (N,) projected masses ``M`` of (N, H, W) ``projections`` (less ``floor`` per
    pixel) to ``a + b / |cos(theta)|`` as ``M |cos| = a |cos| + b``; ``b``'s standard error
    from the residual scatter of the views.

    Fewer than three views, or tilts that span no range of ``|cos|``: no evidence (b = 0).
    """
    p = np.asarray(projections, dtype=np.float64)
    cos = np.abs(np.cos(np.deg2rad(np.asarray(angles_deg, dtype=np.float64))))
    mass = (p - floor).sum(axis=(1, 2))
    if len(mass) < 3 or np.ptp(cos) <= 1e-6:
        return FilmEvidence(float(mass.mean()) if len(mass) else 0.0, 0.0, 0.0)
    design = np.stack([cos, np.ones_like(cos)], axis=1)
    y = mass * cos
    coef, *_ = np.linalg.lstsq(design, y, rcond=None)
    residual = y - design @ coef
    dof = len(mass) - 2
    scatter = float(residual @ residual) / dof if dof > 0 else 0.0
    cov = scatter * np.linalg.inv(design.T @ design)
    return FilmEvidence(float(coef[0]), float(coef[1]), float(np.sqrt(max(cov[1, 1], 0.0))))


def slab_half_width(detector_half_width: float, half_thickness: float, angles_deg: np.ndarray) -> float:
    """How far from the tilt axis (same units) the rays that reach the detector cross a slab.

    A ray at detector coordinate ``u`` and tilt ``theta`` meets depth ``z`` at
    ``x = (u + z sin(theta)) / cos(theta)``; over ``|u| <= detector_half_width`` and
    ``|z| <= half_thickness`` the largest ``|x|`` is at the steepest tilt.
    """
    theta = np.deg2rad(np.abs(np.asarray(angles_deg, dtype=np.float64)))
    if len(theta) == 0:
        return float(detector_half_width)
    reach = (detector_half_width + half_thickness * np.sin(theta)) / np.cos(theta)
    return float(max(reach.max(), detector_half_width))


@dataclass(frozen=True)
class FieldOfView:
    """The volume the Gaussians fill and the field whose Gaussians are reported (half-sides,
    normalised units), and the start's slice size across the tilt axis (None: the detector's)."""

    half_extent: tuple[float, float, float]
    field_half_extent: tuple[float, float, float]
    slice_px: int | None = None
    evidence: FilmEvidence | None = None
    """The fit that decided it (None when not read: no data, or ``option`` "off")."""
    reach: float = 0.5
    """How far across the tilt axis the rays that reach the detector travel (normalised)."""


def field_of_view(series, projections, length_scale: float, option: str, edge_margin_A: float = 0.0) -> FieldOfView:
    """The volume and the reported field for a tilt series (``series``: angles, pixel size, tilt
    axis and (V, H, W) projections' shape; ``projections`` the (V, H, W) data, array or tensor).

    Both are the cube the detector's longer side spans unless the object is wider than the field
    of view (``option`` "on", or "auto" and :func:`film_evidence` says so): then the volume
    reaches across the tilt axis as far as the rays that reach the detector travel through the
    cube's depth (:func:`slab_half_width`), and along it ``edge_margin_A`` beyond the detector
    (the film goes on there too, and an atom just beyond the edge still puts part of itself on
    the detector's last pixels in every view); the field is the detector."""
    cube = (0.5, 0.5, 0.5)
    if series is None or projections is None or option == "off":
        return FieldOfView(cube, cube)
    evidence = film_evidence(as_array(projections), series.angles_deg)
    if option == "auto" and not evidence.extended:
        return FieldOfView(cube, cube, evidence=evidence)
    across = 0 if series.tilt_axis == "y" else 1
    n_across = series.projections.shape[1 + across]
    detector_half = 0.5 * n_across * series.pixel_size_A * length_scale
    reach = slab_half_width(detector_half, 0.5, series.angles_deg)
    along_half = 0.5 * series.projections.shape[2 - across] * series.pixel_size_A * length_scale
    half, field = list(cube), list(cube)
    half[across], field[across] = max(reach, 0.5), detector_half
    half[1 - across], field[1 - across] = along_half + edge_margin_A * length_scale, along_half
    slice_px = 2 * int(np.ceil(reach / (series.pixel_size_A * length_scale))) + 1
    return FieldOfView(tuple(half), tuple(field), slice_px, evidence, reach)
