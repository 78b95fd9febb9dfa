"""What a reader returns: the projection stack and what its file says about it.  No nerfstudio import."""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np


@dataclass
class StackData:
    """A projection stack as read: ``(N, H, W)`` after moving the tilt axis first."""

    projections: np.ndarray
    pixel_size_A: float | None = None
    angles_deg: np.ndarray | None = None
    imod_tilt_axis_angle_deg: float | None = None
    """The tilt-axis angle IMOD records in an MRC header's labels ("Tilt axis angle = -86.0"),
    counterclockwise from Y (the rows)."""


def imod_tilt_axis_angle(labels: list[str]) -> float | None:
    """The last "Tilt axis angle = A" IMOD wrote into MRC labels (newstack, alignment), or None."""
    found = None
    for label in labels:
        match = re.search(r"tilt axis angle\s*=\s*([-+]?\d+(?:\.\d*)?)", label, re.IGNORECASE)
        if match:
            found = float(match.group(1))
    return found
