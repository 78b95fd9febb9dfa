"""What a set of Gaussians predicts of views: their projections through a kernel
(:func:`predicted_views`), each view's own registration to it (:func:`best_registration`), the shifts a fit's residual
still holds (:func:`residual_shifts`) and
the residual over views a fit did not see (:func:`held_out_rms`).  A fit's residual always
prefers more parameters; views held out of it tell the choices apart (per-view shifts and gains,
:func:`gaussian_atoms_method.engine.run.choose_registration`; kernels, ``held-out-views``).
Pure numpy and torch."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from gaussian_atoms_method.atoms.atom_set import AtomSet, read_atoms
from gaussian_atoms_method.physics.geometry import pixel_centres
from gaussian_atoms_method.physics.projector import project_gaussians
from gaussian_atoms_method.physics.psf import KERNEL_WIDTHS_A, apply_kernel, kernel_margin_of, widened


def predicted_views(atoms: AtomSet, series, kernel_weights=None, chunk: int = 4) -> np.ndarray:
    """(V, H, W) projections of ``atoms`` (with ``sigmas`` and ``amplitudes``, Å in the series'
    output frame) in the views of ``series``, through the kernel of ``kernel_weights`` (fractions
    at :data:`..physics.psf.KERNEL_WIDTHS_A`; None: none), in the series' data units.  With a
    kernel, each view is projected on a detector widened by
    :data:`~..physics.psf.KERNEL_MARGIN_WIDTHS` of its narrowest width, blurred there and cut
    back, as the fit renders a film (an atom just beyond the field sends its tails into it)."""
    if atoms.sigmas is None or atoms.amplitudes is None:
        raise ValueError("atoms need sigmas and amplitudes (a run's atoms.xyz) to be projected")
    _, h, w = series.projections.shape
    if len(atoms) == 0:  # nothing to project
        return np.zeros(series.projections.shape)
    centre = series.centre_px if series.centre_px is not None else ((h - 1) / 2.0, (w - 1) / 2.0)
    rows = torch.as_tensor(pixel_centres(h, series.pixel_size_A, centre[0]))
    cols = torch.as_tensor(pixel_centres(w, series.pixel_size_A, centre[1]))
    margin = 0
    if kernel_weights is not None and np.any(np.asarray(kernel_weights) != 0):
        margin = kernel_margin_of(KERNEL_WIDTHS_A[0], series.pixel_size_A)
        rows, cols = widened(rows, margin, series.pixel_size_A), widened(cols, margin, series.pixel_size_A)
    axes = torch.as_tensor(series.detector_axes())
    means = torch.as_tensor(
        np.asarray(atoms.positions, dtype=np.float64) - np.asarray(series.origin_A, dtype=np.float64)
    )
    sigmas, amps = (
        torch.as_tensor(atoms.sigmas, dtype=torch.float64),
        torch.as_tensor(atoms.amplitudes, dtype=torch.float64),
    )
    weights = torch.as_tensor(
        np.zeros(len(KERNEL_WIDTHS_A)) if kernel_weights is None else np.asarray(kernel_weights, dtype=np.float64)
    )
    widths = torch.as_tensor(KERNEL_WIDTHS_A, dtype=torch.float64)
    out = []
    for start in range(0, len(axes), chunk):  # bounded memory: (chunk, H, N) at a time
        images = project_gaussians(means, sigmas, amps, axes[start : start + chunk], rows, cols)
        images = apply_kernel(images, series.pixel_size_A, widths, weights)
        out.append(images[:, margin : margin + h, margin : margin + w])
    return torch.cat(out).numpy()


def held_out_rms(
    atoms: AtomSet, series, kernel_weights=None, interior_px: tuple[int, int] = (0, 0), fit_registration: bool = False
) -> float:
    """Root-mean-square of measured minus :func:`predicted_views` over the views of ``series``,
    after one constant per view (least squares on that view) and, with ``fit_registration``, each
    view's own best in-plane shift and gain (:func:`best_registration`: a held-out view's
    misregistration and dose belong to no fit), over the detector's interior (``interior_px``
    rows and columns in from each edge), data units."""
    measured = np.asarray(series.projections, dtype=np.float64)
    predicted = predicted_views(atoms, series, kernel_weights)
    if not fit_registration:
        return float(np.sqrt(np.mean(interior(measured - predicted, interior_px) ** 2)))
    from scipy import ndimage

    moved = []
    for m, p in zip(measured, predicted):
        shift, gain = best_registration(m, p)
        moved.append(gain * ndimage.shift(p, shift, order=3, mode="nearest"))
    residual = interior(measured - np.stack(moved), interior_px)
    return float(np.sqrt(np.mean(residual**2)))


def best_registration(measured: np.ndarray, predicted: np.ndarray, steps: int = 10) -> tuple[np.ndarray, float]:
    """The (2,) in-plane shift (pixels) and the gain that take ``predicted`` (H, W) onto
    ``measured`` in least squares, a constant free (Gauss-Newton on the image's gradients)."""
    from scipy import ndimage

    shift, gain = np.zeros(2), 1.0
    for _ in range(steps):
        moved = ndimage.shift(predicted, shift, order=3, mode="nearest")
        gradient = np.stack(np.gradient(moved))  # d moved / d position = - d moved / d shift
        design = np.c_[-gain * gradient[0].ravel(), -gain * gradient[1].ravel(), moved.ravel(), np.ones(moved.size)]
        solution = np.linalg.lstsq(design, (measured - gain * moved).ravel(), rcond=None)[0]
        shift, gain = shift + solution[:2], gain + solution[2]
        if np.abs(solution[:2]).max() < 1e-4 and abs(solution[2]) < 1e-6 * max(abs(gain), 1e-12):
            break
    return shift, float(gain)


def gauge_free_shifts(shifts: torch.Tensor, axes: torch.Tensor) -> torch.Tensor:
    """(V, 2) per-view detector shifts less the part a translation of the object makes: a
    translation ``t`` shifts view ``v`` by ``P_v t`` (its detector axes ``axes`` (V, 2, 3)), so
    shifts of that form move the atoms, not the views; the least-squares ``t`` is taken out.  What
    a shift the same in every view along the rows holds beyond that (the tilt axis off the
    assumed centre) stays.

    >>> axes = torch.tensor([[[1.0, 0, 0], [0, 1, 0]], [[0.6, 0, -0.8], [0, 1, 0]], [[0.6, 0, 0.8], [0, 1, 0]]])
    >>> bool(gauge_free_shifts(axes @ torch.tensor([0.3, -0.2, 0.5]), axes).abs().max() < 1e-6)
    True
    """
    a = axes.reshape(-1, 3)  # (2V, 3)
    flat = shifts.reshape(-1, 1)
    t = torch.linalg.lstsq(a, flat).solution
    return (flat - a @ t).reshape(shifts.shape)


def residual_shifts(residuals, predicted, detector_axes=None) -> tuple[np.ndarray, float]:
    """Each view's shift (pixels, rows and columns) that its residual holds against the predicted
    view, and whether it is the view's: how strongly the two halves of each view (its upper and
    lower rows) agree on it, in standard errors.

    The residual ``measured - predicted`` of a view shifted by ``s`` with its gain off by ``g`` and
    a constant ``c`` is ``-s . grad(predicted) + g predicted + c`` to first order: per view, a
    least-squares fit of those four (one Gauss-Newton step of :func:`best_registration` about no
    shift).  A view that is off is off in both its halves; noise and the structure no atom
    explains (a probe's tails, a support) differ between them.  Over the V views the halves'
    shifts ``a_v``, ``b_v`` agree by ``sum a.b / sqrt(sum |a|^2 sum |b|^2)``, which for halves
    that share nothing is about normal of standard deviation ``1 / sqrt(2 V)``: the agreement
    times ``sqrt(2 V)`` is returned (3 or more: the views are off).  With the views' detector
    axes the shifts a translation of the object makes (``P_v t``, the same in the object for every
    view: a misfit every view shares, which the atoms themselves take up) are taken out first, as
    :func:`gauge_free_shifts` does.

    Parameters
    ----------
    residuals, predicted : (V, H, W) arrays or tensors
        Measured minus predicted, and the predicted views, in one unit.

    Returns
    -------
    shifts_px : (V, 2) array
    agreement_z : float

    Examples
    --------
    A Gaussian blob seen 0.3 px off along the rows, no noise: the shift comes back (to first
    order: 0.32).

    >>> u = np.arange(32.0)[:, None]
    >>> blob = lambda c: np.exp(-((u - c) ** 2 + (u.T - 16.0) ** 2) / (2 * 2.0**2))
    >>> shifts, _ = residual_shifts((blob(16.3) - blob(16.0))[None], blob(16.0)[None])
    >>> round(float(shifts[0, 0]), 1), abs(float(shifts[0, 1])) < 1e-9
    (0.3, True)
    """
    shifts, _, agreement = residual_registration(residuals, predicted, detector_axes)
    return shifts, agreement


def residual_registration(residuals, predicted, detector_axes=None) -> tuple[np.ndarray, np.ndarray, float]:
    """:func:`residual_shifts`' shifts (V, 2) and agreement, with each view's gain (V,) from the
    same least-squares fit: ``1 + g``, the factor by which the view holds more than predicted."""
    r = torch.as_tensor(residuals, dtype=torch.float64)
    half = r.shape[1] // 2
    found = {"all": [], "upper": [], "lower": []}
    for v in range(len(r)):  # a view at a time: the design is four images of it
        p = torch.as_tensor(predicted[v], dtype=torch.float64, device=r.device)
        rows, cols = torch.gradient(p)
        design = torch.stack([-rows, -cols, p, torch.ones_like(p)], dim=-1)  # (H, W, 4)
        sums = []  # each half's normal equations; the whole view's are their sum
        for part in (slice(0, half), slice(half, None)):
            d, y = design[part].reshape(-1, 4), r[v, part].reshape(-1)
            sums.append((d.T @ d, d.T @ y))
        sums.append((sums[0][0] + sums[1][0], sums[0][1] + sums[1][1]))
        for name, (normal, rhs) in zip(("upper", "lower", "all"), sums):
            normal = normal + torch.diag(1e-12 * torch.diagonal(normal).clamp_min(1e-300))
            found[name].append(torch.linalg.solve(normal, rhs))

    axes = (
        None
        if detector_axes is None
        else torch.as_tensor(np.asarray(detector_axes, np.float64)[:, :2], device=r.device)
    )

    def gauge_free(shifts: torch.Tensor) -> torch.Tensor:
        return shifts if axes is None else gauge_free_shifts(shifts, axes)

    upper, lower = (gauge_free(torch.stack(found[name])[:, :2]) for name in ("upper", "lower"))
    agreement = float((upper * lower).sum() / torch.sqrt((upper**2).sum() * (lower**2).sum()).clamp_min(1e-300))
    whole = torch.stack(found["all"])
    shifts = gauge_free(whole[:, :2]).cpu().numpy()
    return shifts, 1.0 + whole[:, 2].cpu().numpy(), agreement * float(np.sqrt(upper.numel()))


def interior(images: np.ndarray, interior_px: tuple[int, int]) -> np.ndarray:
    """(V, H, W) images cut to the detector's interior (``interior_px`` rows and columns in from
    each edge), less their mean: one constant per view."""
    r0, c0 = interior_px
    images = images[:, r0 : images.shape[1] - r0, c0 : images.shape[2] - c0]
    return images - images.mean(axis=(1, 2), keepdims=True)


def run_gaussians(run_dir: str | Path) -> AtomSet:
    """Every Gaussian a finished run fitted: its ``atoms.xyz`` and, where written, ``non_atoms.xyz``
    (the film beyond the field, the non-atoms: they explain the views as much as the atoms do)."""
    parts = [read_atoms(Path(run_dir) / "atoms.xyz")]
    if (Path(run_dir) / "non_atoms.xyz").is_file():
        parts.append(read_atoms(Path(run_dir) / "non_atoms.xyz"))
    parts = [p for p in parts if len(p)]
    if not parts:  # a fit that kept no Gaussian predicts empty views
        return AtomSet(positions=np.zeros((0, 3)), sigmas=np.zeros(0), amplitudes=np.zeros(0))
    return AtomSet(
        positions=np.concatenate([p.positions for p in parts]).reshape(-1, 3),
        sigmas=np.concatenate([p.sigmas for p in parts]),
        amplitudes=np.concatenate([p.amplitudes for p in parts]),
    )


def run_kernel(run_dir: str | Path) -> list[float] | None:
    """The point-spread function's intensity fractions a finished run ended with
    (``psf.json``), None where it had none."""
    import json

    path = Path(run_dir) / "psf.json"
    return json.loads(path.read_text())["intensity_fractions"] if path.is_file() else None
