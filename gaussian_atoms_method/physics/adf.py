"""ADF-STEM views through physics the fit does not share: projected atomic potentials, a probe from
its optics, scan jitter.

The fit draws every atom as one isotropic Gaussian through a Gaussian-ladder blur.  A replica
that draws atoms the same way measures almost nothing of the fit's own error (its profile, its
blur), so the replica (:mod:`.replica`) draws them here instead:

* each atom's image is a power of the projected potential of its element (Lobato or
  Kirkland: a sharp core and long tails), drawn at its exact place in each view's detector frame
  (any orientation: tilts or Euler angles);
* the contrast is ADF-like: incoherent, linear in the atoms, each atom's integrated intensity
  ``Z^n`` (:data:`ADF_EXPONENT`) (:func:`adf_projections`);
* the probe is formed by its optics: voltage, convergence semi-angle, defocus, Cs, a Gaussian
  effective source and an optional halo (:func:`.microscope.aberrated_probe_intensity`);
* the scan moves each line of a view a little along the fast axis (:func:`scan_jitter`).

Lobato's potentials are computed here from their parameters (:mod:`.lobato`); Kirkland's come
through abTEM, the optional extra ``gaussian-atoms[sim]``.
"""

from __future__ import annotations

import functools

import numpy as np

from gaussian_atoms_method.physics.lobato import lobato_projected_potential_VA

ADF_EXPONENT = 1.7
"""ADF-STEM's intensity per atom grows as ``Z^n`` with ``n`` 1.6-1.9 over the usual detector
angles (Pennycook's incoherent imaging; Rutherford's ``Z^2`` screened): the middle of it."""

MARGIN_A = 5.0
"""Atoms are drawn whose projected centre lies within this of the detector, on a periodic grid
padded by as much on each side, so the periodic images of them fall at least this far outside
the detector: the ADF kernel of a Ta atom 5 Å out is under 1e-5 of its value 1 Å out."""

ADF_POTENTIAL_POWER = 1.7
"""The power of the projected potential that is an atom's ADF image (:func:`adf_kernel_transform`).
High-angle scattering comes from near the nucleus, so an ADF image is far more local than the
potential; a projected potential's core grows about as ``Z`` and ADF intensity as ``Z^1.6-1.9``
(:data:`ADF_EXPONENT`), so the power that carries the one to the other is the middle of it."""


def _projected_potential(element: str, parametrization: str):
    """``element``'s projected potential as a callable of the radius (Å): Lobato's from its
    parameters (:mod:`.lobato`, no simulator needed), Kirkland's through abTEM."""
    if parametrization == "lobato":
        return functools.partial(lobato_projected_potential_VA, element)
    if parametrization != "kirkland":
        raise ValueError(f"parametrization must be 'lobato' or 'kirkland', got {parametrization!r}")
    try:
        from abtem import parametrizations
    except ImportError as exc:  # pragma: no cover - depends on the optional extra
        raise ImportError("Kirkland potentials come through abTEM: pip install 'gaussian-atoms[sim]'") from exc
    return parametrizations.KirklandParametrization().projected_potential(element)


def adf_weights(species) -> np.ndarray:
    """(N,) each atom's integrated ADF intensity, ``Z^``:data:`ADF_EXPONENT`, from its element.

    >>> adf_weights(["C", "Ta"]).round(1).tolist()
    [21.0, 1471.1]
    """
    from ase.data import atomic_numbers

    return np.array([atomic_numbers[s] for s in species], dtype=np.float64) ** ADF_EXPONENT


@functools.lru_cache(maxsize=32)
def adf_kernel_transform(
    element: str, parametrization: str = "lobato", power: float = ADF_POTENTIAL_POWER, k_max: float = 4.0
) -> tuple[np.ndarray, np.ndarray]:
    """The radial Fourier transform of one atom's ADF image, ``P(r)^power`` with ``P`` the
    projected potential of ``element``, normalised to unit integral: ``(k, K^(k))`` on 1,201
    spatial frequencies from 0 to ``k_max`` (1/Å), by a Hankel transform over 0-12 Å.

    >>> k, t = adf_kernel_transform("Ta")
    >>> float(t[0]), bool(t[300] < t[0])
    (1.0, True)
    """
    from scipy.special import j0

    profile = _projected_potential(element, parametrization)
    r = np.r_[np.geomspace(1e-6, 0.05, 600, endpoint=False), np.linspace(0.05, 12.0, 6000)]
    image = np.asarray(profile(r), dtype=np.float64) ** power
    k = np.linspace(0.0, k_max, 1201)
    transform = np.array([np.trapezoid(2 * np.pi * r * image * j0(2 * np.pi * kk * r), r) for kk in k])
    return k, transform / transform[0]


def adf_projections(
    positions_A: np.ndarray,
    species,
    weights: np.ndarray,
    detector_axes: np.ndarray,
    image_shape: tuple[int, int],
    pixel_size_A: float,
    centre_px: tuple[float, float],
    parametrization: str = "lobato",
    probe=None,
    oversample: int = 2,
    method: str = "exact",
    power: float = ADF_POTENTIAL_POWER,
) -> np.ndarray:
    """(V, H, W) incoherent ADF views of atoms: each atom's image the power ``power``
    (:data:`ADF_POTENTIAL_POWER`) of its element's projected potential (``parametrization``,
    :func:`adf_kernel_transform`), carrying the integrated intensity ``weights`` (per Å² of the
    detector: the same units as a Gaussian of integrated mass ``weights``).

    Each view is drawn in Fourier space on a periodic grid padded by :data:`MARGIN_A` and
    ``oversample`` times finer than the detector: the atoms' phases at their exact positions (no
    pixel snapping or interpolation), times each element's kernel and the probe's transfer, then
    sampled at the pixel centres as a scan samples the probe's image (what lies beyond the
    detector's Nyquist frequency aliases, as it does in a microscope).  The probe must be drawn
    here: an atom's image is sharper than the fine grid, and only the probe band-limits it.

    Parameters
    ----------
    positions_A : (N, 3) array
        Atoms about the tilt centre, Å.
    species : (N,) sequence of str
    weights : (N,) array
        Each atom's integrated intensity (``Z^n`` for ADF contrast).
    detector_axes : (V, 3, 3) array
        Each view's row, column and beam directions (:mod:`~gaussian_atoms_method.physics.geometry`).
    image_shape : (H, W)
    pixel_size_A : float
    centre_px : (2,)
        The tilt centre on the detector, pixels.
    parametrization : {"lobato", "kirkland"}
    probe : callable, optional
        ``probe(shape, spacing_A)``: the probe intensity's transform on a periodic grid
        (:meth:`.microscope.ProbeOptics.transfer`); None: a point probe.
    oversample : int
        The fine grid's pixels per detector pixel: its Nyquist frequency must hold the probe's
        (``2 alpha / lambda``: 2.0 / Å at 20 mrad and 300 kV, held by 2 at pixels up to 0.37 Å).
    method : {"exact", "deposit"}
        ``"exact"``: each atom's phases at its exact place, ``O(N G^2)`` per view for N atoms on a
        G x G grid.  ``"deposit"``: each atom's intensity shared among its four nearest points of
        a grid :data:`DEPOSIT_OVERSAMPLE` times finer than the detector (cloud in cell), that
        sharing's own transfer divided out, ``O(N + G^2 log G)`` (:func:`_deposit_spectrum`);
        ``oversample`` is then not used.
    power : float
        The power of the projected potential that is an atom's image (1: the potential itself, as
        a phase image draws it, :mod:`.phase`).
    """
    if method not in ("exact", "deposit"):
        raise ValueError(f"method must be 'exact' or 'deposit', got {method!r}")
    oversample = DEPOSIT_OVERSAMPLE if method == "deposit" else oversample
    positions = np.asarray(positions_A, dtype=np.float64)
    species = np.asarray(species)
    weights = np.asarray(weights, dtype=np.float64)
    h, w = image_shape
    pad = int(np.ceil(MARGIN_A / pixel_size_A))
    fine = pixel_size_A / oversample
    grid = ((h + 2 * pad) * oversample, (w + 2 * pad) * oversample)
    origin = (np.asarray(centre_px, dtype=np.float64) + pad) * pixel_size_A
    lo = pad * pixel_size_A - MARGIN_A
    hi = (np.array([h - 1, w - 1]) + pad) * pixel_size_A + MARGIN_A
    k_rows = np.fft.fftfreq(grid[0], d=fine)
    k_cols = np.fft.fftfreq(grid[1], d=fine)
    k_abs = np.hypot(k_rows[:, None], k_cols[None, :])
    blur = np.ones(grid) if probe is None else probe(grid, fine)
    transfers = {}
    for element in sorted(set(species.tolist())):
        k, t = adf_kernel_transform(element, parametrization, power, k_max=float(k_abs.max()) * 1.001)
        transfer = np.interp(k_abs, k, t) * blur
        transfers[element] = (species == element, transfer.astype(np.complex64) if method == "deposit" else transfer)
    out = np.zeros((len(detector_axes), h, w), dtype=np.float64)
    crop = (slice(pad, pad + h), slice(pad, pad + w))
    for v, axes in enumerate(np.asarray(detector_axes, dtype=np.float64)):
        local = positions @ axes[:2].T + origin
        seen = np.all((local >= lo) & (local <= hi), axis=1)
        spectrum = np.zeros(grid, dtype=np.complex64 if method == "deposit" else np.complex128)
        for mine, transfer in transfers.values():
            chosen = mine & seen
            if not chosen.any():
                continue
            if method == "deposit":
                spectrum += transfer * _deposit_spectrum(local[chosen] / fine, weights[chosen], grid)
                continue
            rows = np.exp(-2j * np.pi * np.outer(local[chosen, 0], k_rows)) * weights[chosen, None]
            cols = np.exp(-2j * np.pi * np.outer(local[chosen, 1], k_cols))
            spectrum += transfer * (rows.T @ cols)
        if method == "deposit":  # sampled at the pixels: the spectrum folded onto the detector's grid
            folded = spectrum.reshape(oversample, grid[0] // oversample, oversample, grid[1] // oversample).sum((0, 2))
            out[v] = (np.fft.ifft2(folded).real / (oversample**2 * fine**2))[crop]
            continue
        out[v] = (np.fft.ifft2(spectrum).real[::oversample, ::oversample] / fine**2)[crop]
    return out


DEPOSIT_OVERSAMPLE = 4
"""The deposit's grid pitch is a quarter of a pixel: at 0.4 Å pixels (0.1 Å) the probe's highest
frequency (2.0 / Å at 20 mrad, 300 kV) lies at a fifth of the grid's sampling frequency, where the
images of the sharing's own transfer that alias back weigh under 3% of an atom's spectrum there
and under 0.3% at a tenth of it."""


def _deposit_spectrum(at_px: np.ndarray, weights: np.ndarray, grid: tuple[int, int]) -> np.ndarray:
    """The spectrum (``grid``, numpy's FFT order) of point intensities ``weights`` (N,) at
    ``at_px`` (N, 2) on a periodic grid (in its pixels): each shared bilinearly among its four
    nearest points, the sharing's transfer (``sinc^2`` along each axis) divided out.

    >>> spectrum = _deposit_spectrum(np.array([[3.25, 5.5]]), np.array([2.0]), (16, 16))
    >>> round(float(spectrum[0, 0].real), 12)
    2.0
    """
    base = np.floor(at_px).astype(np.int64)
    frac = at_px - base
    # the four shares of every point in one count (one grid-sized array, not four: each is a
    # fresh allocation the system pages in)
    corners = ((0, 0), (0, 1), (1, 0), (1, 1))
    share = np.concatenate(
        [
            weights * np.where(dr, frac[:, 0], 1 - frac[:, 0]) * np.where(dc, frac[:, 1], 1 - frac[:, 1])
            for dr, dc in corners
        ]
    )
    index = np.concatenate(
        [((base[:, 0] + dr) % grid[0]) * grid[1] + (base[:, 1] + dc) % grid[1] for dr, dc in corners]
    )
    flat = np.bincount(index, weights=share, minlength=grid[0] * grid[1])
    from scipy import fft

    return fft.fft2(flat.reshape(grid).astype(np.float32), workers=-1) / _sharing_transfer(grid)


@functools.lru_cache(maxsize=4)
def _sharing_transfer(grid: tuple[int, int]) -> np.ndarray:
    """The bilinear sharing's transfer on ``grid``, ``sinc^2`` along each axis (float32; one per
    grid, read by every view: read-only)."""
    sharing = np.outer(np.sinc(np.fft.fftfreq(grid[0])) ** 2, np.sinc(np.fft.fftfreq(grid[1])) ** 2).astype(np.float32)
    sharing.setflags(write=False)
    return sharing


def scan_jitter(views: np.ndarray, rms_px: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``views`` (V, H, W) with each scan line (a row) moved along the fast axis (the columns) by
    its own random shift of RMS ``rms_px`` (linear interpolation, edges held), and the shifts (V, H).
    A STEM scan places each line a little off where it should be: jitter that no view shares."""
    views = np.asarray(views, dtype=np.float64)
    shifts = rng.normal(0.0, rms_px, size=views.shape[:2]) if rms_px > 0 else np.zeros(views.shape[:2])
    if rms_px <= 0:
        return views.copy(), shifts
    cols = np.arange(views.shape[2], dtype=np.float64)
    out = np.empty_like(views)
    for v in range(views.shape[0]):
        for r in range(views.shape[1]):
            out[v, r] = np.interp(cols - shifts[v, r], cols, views[v, r])
    return out, shifts
