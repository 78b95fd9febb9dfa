"""The fit's residuals over every training view, and Gaussians added where they show mass.

:func:`render_training_views` renders the model in every training view (full resolution,
background included); :func:`add_missing_atoms` back-projects measured minus predicted and adds
a Gaussian at each site of significant unexplained mass
(:func:`gaussian_atoms_method.atoms.residual_sites.unexplained_sites`), through the density
strategy (:meth:`gaussian_atoms_method.density.strategy.DensityControl.add`);
:func:`say_view_shifts` says whether the final residual still holds each view shifted.
"""

from __future__ import annotations

from contextlib import contextmanager

import numpy as np
import torch

from gaussian_atoms_method.atoms.residual_sites import unexplained_sites
from gaussian_atoms_method.engine.console import CONSOLE
from gaussian_atoms_method.engine.rendering import (
    pixel_coordinates,
    render_views,
    to_device_without_waiting,
    view_chunks,
)
from gaussian_atoms_method.engine.views import views_from_tilt_series


@contextmanager
def training_views(model):
    """The cameras of the model's training views (None without the tilt series), with the
    model in eval mode meanwhile: full resolution, one view per call, whatever the phase."""
    series = model.view_set.series
    if series is None:
        yield None
        return
    cameras = views_from_tilt_series(series, model.normalisation).to(model.means.device)
    training = model.training
    model.eval()
    try:
        yield cameras
    finally:
        model.train(training)


@torch.no_grad()
def render_training_views(model, on_device: bool = False) -> np.ndarray | torch.Tensor | None:
    """(V, H, W) the model's projections of its training views (normalised data units): an
    array, or with ``on_device`` a tensor on the model's device; None without the tilt series."""
    with training_views(model) as cameras:
        if cameras is None:
            return None
        batched = in_chunks(model, cameras)
        if batched is not None:
            rows, cols, pitch, chunks = batched
            views = torch.cat([render_views(model, chunk, rows, cols, pitch) for chunk in chunks])
        else:  # per view, each through its own pose
            views = torch.stack(
                [model.get_outputs(cameras[i : i + 1])["projection"][..., 0] for i in range(len(cameras))]
            )
        return views if on_device else views.cpu().numpy()


def measured_views(model) -> torch.Tensor | None:
    """(V, H, W) the measured training views (normalised data units) on the model's device,
    copied there without waiting for its queued work (:func:`.rendering.to_device_without_waiting`:
    a plain copy to the GPU waits for it); None without the tilt series."""
    projections = model.view_set.projections
    return None if projections is None else to_device_without_waiting(torch.as_tensor(projections), model.means.device)


def in_chunks(model, cameras):
    """(rows, cols, pitch, chunks) to render the model's training ``cameras`` a chunk of views at
    a time, one projector call each (:func:`.rendering.render_views`, :func:`.rendering.view_chunks`,
    not a call of a few dozen operations per view), or None where each view needs its own pose
    (learned shifts or tilts, anisotropic Gaussians, cameras off their beam axes)."""
    if not model.indexed_views or len(cameras) != model.view_c2w.shape[0]:
        return None
    dev, dt = model.means.device, model.means.dtype
    rows, cols = pixel_coordinates(cameras[0:1], cameras.camera_to_worlds[0].to(dt), False, dev, dt)
    pitch = float(rows[1] - rows[0]) if len(rows) > 1 else None
    return rows, cols, pitch, view_chunks(len(cameras), model.num_points, len(rows), len(cols), dev)


@torch.no_grad()
def add_missing_atoms(model) -> int:
    """Add a Gaussian at every site where the residuals hold significant unexplained mass; the
    new ones take the Gaussians' median width.  Returns how many were added."""
    series, projections = model.view_set.series, model.view_set.projections
    predicted = render_training_views(model)
    if predicted is None or projections is None or model.num_points == 0:
        return 0
    ls = model.normalisation.length_scale
    sigma_A = float(model.sigmas.median()) / ls
    hard_core = model.density.hard_core(model.gauss_params)  # normalised units; infinite where unknown
    sites_A, masses = unexplained_sites(
        projections.cpu().numpy() - predicted,
        series.angles_deg,
        series.pixel_size_A,
        model.means.detach().cpu().double().numpy() / ls,
        sigma_A,
        series.tilt_axis,
        series.centre_px,
        false_alarm_rate=model.config.false_alarm_rate,
        tilt_axis_angle_deg=series.tilt_axis_angle_deg,
        device=str(model.means.device),
        hard_core_A=hard_core / ls if np.isfinite(hard_core) else None,
    )
    means = torch.as_tensor(sites_A * ls, dtype=model.means.dtype).reshape(-1, 3)
    # With no site, add() notes that the residuals are clean (no more searches).
    added = model.density.add(
        model.gauss_params, model.optimizers, means, sigma_A * ls, torch.as_tensor(masses * ls**2), model._param_lists()
    )
    if added:
        CONSOLE.print(
            f"gaussian-atoms: step {model.step}: {added} Gaussians added where the residuals hold unexplained mass"
        )
    split = model.density.split_heavy_gaussians(model.gauss_params, model.optimizers, model._param_lists())
    if split:
        model.density.state.residual_clean = False  # train on and search again
        CONSOLE.print(
            f"gaussian-atoms: step {model.step}: {split} Gaussians heavier than a single atom split in two along the "
            f"least-resolved direction"
        )
    return added + split


def residual_correlations(model, means: torch.Tensor, sigmas: torch.Tensor) -> np.ndarray | None:
    """(P,) for probe Gaussians of unit amplitude at ``means`` (P, 3) with widths ``sigmas``
    (P,) (normalised units): ``sum over views and pixels of w r g``, with ``r`` the residual
    (measured minus the model's projection), ``g`` the probe's projection and ``w`` one over
    the noise variance at the pixel's predicted level.  A Gaussian of amplitude ``A`` explains
    ``A`` times its probe's value of the residual's chi-square, to first order: what
    :meth:`..density.strategy.DensityControl.merge_by_likelihood` needs to tell which of a pair and
    its merged Gaussian the data prefer.  None without the tilt series or a noise model, or for
    anisotropic Gaussians.

    Computed as the gradient of ``sum w r g`` with respect to the probes' log-amplitudes at
    zero: the probes are rendered by the model's own projector (same geometry, view shifts and
    tilts included) in place of its Gaussians, which are put back after.
    """
    noise, measured = model.density.noise, measured_views(model)
    if measured is None or noise is None or not model.config.isotropic or len(means) == 0:
        return None
    own = model.gauss_params
    probe = torch.nn.ParameterDict(
        {
            "means": torch.nn.Parameter(means.detach().to(own["means"])),
            "log_sigmas": torch.nn.Parameter(torch.log(sigmas.detach().to(own["means"]))[:, None]),
            "log_amplitudes": torch.nn.Parameter(
                torch.zeros(len(means), 1, dtype=own["means"].dtype, device=own["means"].device)
            ),
        }
    )
    # on the run's device throughout: one copy back, of the (P,) sums
    predicted = render_training_views(model, on_device=True)
    if predicted is None:
        return None
    weighted = (measured - predicted) / noise.variance(predicted).clamp_min(1e-30)  # w r
    total = torch.zeros(len(means), dtype=torch.float64, device=predicted.device)
    with training_views(model) as cameras, torch.inference_mode(False), torch.enable_grad():
        model.gauss_params = probe
        try:
            batched = in_chunks(model, cameras)  # the floors do not depend on the probes: left out
            images = (
                ((chunk, render_views(model, chunk, *batched[:3], floors=False)) for chunk in batched[3])
                if batched
                else (
                    (v, model.get_outputs(cameras[v : v + 1])["projection"][None, ..., 0]) for v in range(len(cameras))
                )
            )
            for views, image in images:
                (grad,) = torch.autograd.grad((image * weighted[views].to(image)).sum(), probe["log_amplitudes"])
                total += grad[:, 0].detach().double()
        finally:
            model.gauss_params = own
    return total.cpu().numpy()


def say_view_shifts(residuals, predicted, detector_axes, registered: bool) -> dict:
    """Say how far the views sit off the fitted atoms
    (:func:`~gaussian_atoms_method.atoms.view_prediction.residual_shifts` of the final residual,
    measured minus predicted, and the predicted views; less what a translation of the object
    makes in views of ``detector_axes`` (V, 2, 3)) and, where the two halves of the views agree
    on their shifts by 3 standard errors or more and the run learned no shifts (``registered``),
    that overlapping sub-areas can say whether learning them helps (:mod:`..film.registration`;
    views the fit did not see share its systematic errors).  A significant shift
    may still be harmless; one of a fraction of a pixel can place atoms wrong along the beam,
    confidently (the real views' misregistration in a replica: 0.964 found, 29 pm; with
    per-view shifts 0.996, 3.9 pm).  Returns ``view_shifts_rms_px`` (rows, columns) and
    ``view_shifts_z``, and each view's shift and gain against the atoms (``view_offsets_px`` (V, 2),
    ``view_gain_offsets`` (V,)): the misregistration an internal replica is given
    (:mod:`gaussian_atoms_method.harness.internal_floor`)."""
    from gaussian_atoms_method.atoms.view_prediction import residual_registration

    shifts, gains, z = residual_registration(residuals, predicted, detector_axes)
    rms = np.sqrt(np.mean(shifts**2, axis=0))
    words = (
        f"the views sit {rms[0]:.2f} / {rms[1]:.2f} px RMS along rows / columns off the fitted atoms (up to "
        f"{np.abs(shifts).max():.2f} px; each view's halves agree on it by {z:.1f} standard errors)"
    )
    if z >= 3.0 and not registered:
        words += (
            ": a shift the views hold; whether learning it helps a lone series cannot say, overlapping sub-areas "
            "can (gaussian-atoms film --registration-by-overlap; --pipeline.model.refine-alignment True learns it)"
        )
    CONSOLE.print(f"gaussian-atoms: {words}")
    return {
        "view_shifts_rms_px": [float(x) for x in rms],
        "view_shifts_z": float(z),
        "view_offsets_px": shifts.tolist(),
        "view_gain_offsets": gains.tolist(),
    }


def learned_registration(model) -> tuple[np.ndarray, np.ndarray] | None:
    """Each view's learned shift ((V, 2) rows, columns; pixels, the shifts a translation of the
    object makes taken out, the content's own displacement as ``scipy.ndimage.shift`` moves it)
    and gain ((V,), against the views' mean); None where the run learned neither
    (``refine_alignment``, ``refine_gain``) or knows no pixel size."""
    from gaussian_atoms_method.atoms.view_prediction import gauge_free_shifts
    from gaussian_atoms_method.engine.rendering import detector_axes, view_gain

    params, pixel_A = model.view_params, model.view_set.pixel_size_A
    if pixel_A is None or not ({"view_shifts", "view_gains"} & set(params.keys())):
        return None
    n_views = model.view_c2w.shape[0]
    shifts, gains = np.zeros((n_views, 2)), np.ones(n_views)
    with torch.no_grad():
        if "view_shifts" in params:
            axes = detector_axes(model.view_c2w.detach().cpu().double())
            free = gauge_free_shifts(params["view_shifts"].detach().cpu().double(), axes)
            shifts = free.numpy() / model.normalisation.length_scale / pixel_A
        if "view_gains" in params:
            log_gains = params["view_gains"].detach().cpu().double()
            gains = np.array([float(view_gain(log_gains, v)) for v in range(n_views)])
    return shifts, gains


def write_learned_registration(model, run_dir) -> tuple[np.ndarray, np.ndarray] | None:
    """Write :func:`learned_registration` to ``run_dir/registration.csv``, say it in a line and
    return it (nothing, and None, where the run learned no registration): the misregistration a replica of the
    experiment can be given (``gaussian-atoms simulate --like DIR --shifts-from FILE``)."""
    from dataparsers.registration_file import write_registration

    learned = learned_registration(model)
    if learned is None:
        return None
    shifts, gains = learned
    run_dir.mkdir(parents=True, exist_ok=True)
    write_registration(run_dir / "registration.csv", shifts, gains)
    rms, said = np.sqrt(np.mean(shifts**2, axis=0)), []
    if "view_shifts" in model.view_params:
        said.append(
            f"shifts {rms[0]:.2f} / {rms[1]:.2f} px RMS along rows / columns (up to {np.abs(shifts).max():.2f} px)"
        )
    if "view_gains" in model.view_params:
        said.append(f"gains scattered {np.std(gains):.1%}")
    CONSOLE.print(
        f"gaussian-atoms: the views' learned registration: {', '.join(said)} (registration.csv; a replica of the "
        f"experiment takes its shifts: gaussian-atoms simulate --like DATA --shifts-from registration.csv)"
    )
    return learned
