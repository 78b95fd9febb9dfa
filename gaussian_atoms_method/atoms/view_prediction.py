"""What a set of Gaussians predicts of views: their projections through a kernel
(:func:`predicted_views`), each view's own registration to it (:func:`best_registration`) and
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
from gaussian_atoms_method.physics.psf import KERNEL_WIDTHS_A, apply_kernel


def predicted_views(atoms: AtomSet, series, kernel_weights=None, chunk: int = 4) -> np.ndarray:
    """(V, H, W) projections of ``atoms`` (with ``sigmas`` and ``amplitudes``, Å in the series'
    output frame) in the views of ``series``, through the kernel of ``kernel_weights`` (fractions
    at :data:`..physics.psf.KERNEL_WIDTHS_A`; None: none), in the series' data units."""
    if atoms.sigmas is None or atoms.amplitudes is None:
        raise ValueError("atoms need sigmas and amplitudes (a run's atoms.xyz) to be projected")
    _, h, w = series.projections.shape
    if len(atoms) == 0:  # nothing to project
        return np.zeros(series.projections.shape)
    centre = series.centre_px if series.centre_px is not None else ((h - 1) / 2.0, (w - 1) / 2.0)
    rows = torch.as_tensor(pixel_centres(h, series.pixel_size_A, centre[0]))
    cols = torch.as_tensor(pixel_centres(w, series.pixel_size_A, centre[1]))
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
        out.append(apply_kernel(images, series.pixel_size_A, widths, weights))
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
