"""Where the Gaussians start: candidate atom sites from a smoothed back-projection.

The paper starts from about 10,000 Gaussians at random positions and relies on gradient-driven
duplication to reach every atom.  Measured on the 6,679-atom Au particle (limited tilts), that
leaves 6-10% of the atoms with no Gaussian near them: a neighbour widens to absorb an empty
site's signal and the pull that would trigger duplication cancels.  A filtered back-projection
already shows where the mass is, so we start there:

1. FBP with a Hann filter (the ramp filter's high frequencies are mostly noise at atomic
   resolution);
2. smoothing with a Gaussian of ``smoothing_A`` (0.5 Å, about a blurred atom's width): a
   matched filter for atom-shaped peaks;
3. local maxima taken strongest first, at least ``min_distance_A`` apart (1.5 Å: less than any
   interatomic distance, so no atom is shadowed by a neighbour's candidate), capped at
   ``max_count``.

Measured recall (a candidate within 1.2 Å of every true atom, 10,000 candidates, Au limited,
Lobato potentials): 1.000 at noise 50, 0.9998 at noise 200, 0.994 at noise 500; the ramp
filter without smoothing reaches 0.83 and 0.46 at noise 200 and 500.  Surplus candidates are
noise: the fit drives their mass down and the prune removes them.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from .baselines import reconstruct
from .tracing import local_maxima, suppress_within


def backprojection_candidates(
    projections: np.ndarray,
    angles_deg: np.ndarray,
    pixel_size_A: float,
    tilt_axis: str = "y",
    centre_px=None,
    max_count: int = 10000,
    smoothing_A: float = 0.5,
    min_distance_A: float = 1.5,
) -> np.ndarray:
    """Candidate atom positions, strongest first.

    Parameters
    ----------
    projections : (N, H, W) array
        The tilt series (any units).
    angles_deg : (N,) array
        Single-axis tilt angles, degrees.
    pixel_size_A : float
        Detector pixel size, Å.
    tilt_axis : {"y", "x"}
    centre_px : (2,) floats, optional
        Detector (row, col) of the tilt centre; default the middle.
    max_count : int
        At most this many candidates.
    smoothing_A : float
        Standard deviation of the Gaussian smoothing of the reconstruction, Å.
    min_distance_A : float
        Candidates lie more than this far apart, Å.

    Returns
    -------
    positions_A : (M, 3) array, M <= max_count
        Positions in Å about the tilt centre (world x, y, z), strongest first.
    """
    if max_count <= 0:
        return np.zeros((0, 3))
    volume = reconstruct(projections, angles_deg, pixel_size_A, "fbp", tilt_axis, centre_px, filter_name="hann")
    data = ndimage.gaussian_filter(volume.data, smoothing_A / volume.spacing_A) if smoothing_A > 0 else volume.data
    peaks = local_maxima(data)
    if len(peaks) == 0:
        return np.zeros((0, 3))
    values = data[tuple(peaks.T)]
    order = np.argsort(-values, kind="stable")
    keep = suppress_within(peaks * volume.spacing_A, order, min_distance_A)[:max_count]
    return volume.index_to_A(peaks[keep])
