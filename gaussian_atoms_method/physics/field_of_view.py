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
