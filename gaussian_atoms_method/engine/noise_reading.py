"""What the model reads from the projections before training: the noise, a detector floor and
whether the object is wider than the field of view.

The physics is :mod:`gaussian_atoms_method.physics.noise` (the measurement) and
:mod:`gaussian_atoms_method.physics.data_terms` (the choice of term); this puts the options'
``auto`` values into effect and says on one line what was read and chosen.
"""

from __future__ import annotations

import threading
from dataclasses import replace

import numpy as np

from gaussian_atoms_method.atoms.initialise import Start
from gaussian_atoms_method.engine.console import CONSOLE
from gaussian_atoms_method.physics.data_terms import choose_data_term
from gaussian_atoms_method.physics.detector_floor import clipped_frame, detector_floor, frame_mask, frame_surfaces
from gaussian_atoms_method.physics.noise import NoiseModel, as_array, atom_scale_excess, inflated

FLOOR_Z = 5.0
"""A frame level this many standard errors off zero is a real offset: a one-in-3.5-million
false alarm for Gaussian noise, and a fitted constant that starts at zero costs nothing when
the alarm is false."""
FLAT_FRAME_RATIO = 1.5
"""The frame counts as empty background when its pixels vary by at most this many times the
noise variance at its level: a variance estimate from the thousands of frame pixels is good to
a few per cent, the pre-fit noise model to 10-20% (:func:`~gaussian_atoms_method.physics.noise.noise_from_projections`);
atoms reaching the frame (a film, a crowded field) add far more."""


def noise_reading(projections, loss: str, background: str, noise: NoiseModel | None) -> tuple:
    """The noise model of the (V, H, W) normalised projections, ``noise`` as measured
    (:func:`~gaussian_atoms_method.physics.noise.measure_noise`; None: none could be measured),
    the data term to use, the detected floor, for a floor that varies within the views its shape,
    and the line that says them (None without noise; said by :func:`say_noise_reading`).  Host
    work only, so it runs beside the start (:class:`NoiseReadingBeside`).

    With ``background`` "auto" a floor is found when the frame's level sits significantly off
    zero (:data:`FLOOR_Z`) and the frame is background: smooth, when each view's quadratic frame
    surface (:func:`~gaussian_atoms_method.physics.detector_floor.frame_surfaces`) explains the frame
    significantly better than a constant (by :data:`FLOOR_Z` standard errors of the variance)
    and leaves no more than the noise (that surface less its mean is added to the view and a
    constant per view is learned); else flat (a constant per view is learned from the floor).
    Where atoms reach the frame the same is asked of the pixels they leave alone
    (:func:`~gaussian_atoms_method.physics.detector_floor.clipped_frame`); a film's frame, all atoms,
    leaves too few and too rough a floor.  With "smooth" the
    surfaces are used whatever the frame.  Returns (noise, term, floor or None, (V, H, W)
    surfaces or None, line), normalised units."""
    if noise is None:
        return None, ("l1" if loss == "auto" else loss), None, None, None
    data = as_array(projections)
    term = choose_data_term(noise, float(np.percentile(data, 99.9))) if loss == "auto" else loss
    if term == "poisson" and noise.gain <= 0:
        # Forced on additive noise: the Poisson term needs a gain; one count per noise variance
        # makes its weights uniform (it then behaves as L2).
        noise = NoiseModel(0.0, max(noise.read_var, 1e-12), noise.offset, least_mean=noise.least_mean)
    floor, floor_se, frame_var = detector_floor(data)
    off_zero = abs(floor) > FLOOR_Z * floor_se
    found, surfaces, clipped = False, None, False
    if background == "smooth" or (background == "auto" and off_zero):
        surfaces, smooth_var = frame_surfaces(data)
        n_frame = frame_mask(data.shape[-2:]).sum() * len(data)
        found, smooth = _floor_shape(noise, floor, frame_var, smooth_var, n_frame)
        if background == "auto" and not found:
            # Atoms reach the frame: read the floor from the pixels they leave alone.
            surfaces, floor, floor_se, frame_var, smooth_var = clipped_frame(
                data, float(np.sqrt(noise.pixel_variance(np.array([floor]))[0]))
            )
            found, smooth = _floor_shape(noise, floor, frame_var, smooth_var, frame_var / max(floor_se, 1e-300) ** 2)
            found, clipped = found and abs(floor) > FLOOR_Z * floor_se, True
        if background == "smooth" or (found and smooth):
            found, surfaces = True, surfaces - surfaces.mean(axis=(1, 2), keepdims=True)
        else:
            surfaces = None
    said = f"{noise.kind} (read variance {noise.read_var:.3g}, gain {noise.gain:.3g} per count, normalised units)"
    if noise.correlation > 1.0:
        said += (
            f", correlated: the views' spectrum beyond the atoms says the atoms see {noise.correlation:.3g} times the "
            f"variance neighbouring pixels show (interpolated or filtered views)"
        )
    elif not noise.correlation_read:
        said += (
            ", read from neighbouring pixels only: the views' spectrum holds no band beyond the atoms (blurred or "
            "denoised views, or atoms finer than the pixels), so whether their noise is correlated is not known"
        )
    shape = (
        "a floor that varies smoothly within each view (its frame's quadratic surface) and a constant"
        if surfaces is not None
        else "a constant background"
    )
    where = " (its pixels that no atom reaches)" if clipped else ""
    bg = (
        f"; frame level{where} {floor:.3g} ± {floor_se:.1g}: fitting {shape} per view from it"
        if found and background == "auto"
        else ""
    )
    line = f"gaussian-atoms: noise read from the projections: {said}; data term {term}{bg}"
    return noise, term, (floor if found else None), surfaces, line


def say_noise_reading(reading: tuple) -> tuple[NoiseModel | None, str, float | None, np.ndarray | None]:
    """Say :func:`noise_reading`'s line and return the rest of it."""
    *read, line = reading
    if line is not None:
        CONSOLE.print(line)
    return tuple(read)


class NoiseReadingBeside:
    """:func:`noise_reading` in a thread, begun once the noise is measured, while the start's
    candidates are found (the GPU's work and numpy's release the interpreter's lock), not in
    line between the start and the first step.  :meth:`result` hands it over, or reads again in
    line for another noise (a start begun ahead and not taken)."""

    def __init__(self, projections, loss: str, background: str, measured: NoiseModel | None) -> None:
        self.args, self.measured, self.reading, self.error = (projections, loss, background), measured, None, None
        self.thread = threading.Thread(target=self._read, name="gaussian-atoms noise reading")
        self.thread.start()

    def _read(self) -> None:
        try:
            self.reading = noise_reading(*self.args, self.measured)
        except BaseException as error:  # noqa: BLE001 - raised again in the caller's thread
            self.error = error

    def result(self, measured: NoiseModel | None) -> tuple:
        """The reading for ``measured`` (the start's noise)."""
        self.thread.join()
        if measured is not self.measured:
            return noise_reading(*self.args, measured)
        if self.error is not None:
            raise self.error
        return self.reading


def _floor_shape(
    noise: NoiseModel, floor: float, frame_var: float, smooth_var: float, n_pixels: float
) -> tuple[bool, bool]:
    """Whether the frame is background (it varies by at most :data:`FLAT_FRAME_RATIO` times the
    noise variance at ``floor``, about its views' means or their quadratic surfaces) and whether
    it is smooth rather than flat (the surfaces explain it better than the means by more than
    :data:`FLOOR_Z` standard errors of a variance over ``n_pixels``, ``sqrt(2 / n)`` of it)."""
    limit = FLAT_FRAME_RATIO * float(noise.pixel_variance(np.array([floor]))[0])
    varies = frame_var - smooth_var > FLOOR_Z * smooth_var * np.sqrt(2.0 / max(n_pixels, 1.0))
    if varies and smooth_var <= limit:
        return True, True
    return frame_var <= limit, False


def say_start(start: Start, length_scale: float, option: str, ahead: bool = False) -> None:
    """Say on one line each when the object is wider than the field of view (``start.field``,
    ``option`` the extended-object option) and why, and where the Gaussians start (``ahead``:
    found by :mod:`gaussian_atoms_method.launch.start_ahead` while the launcher loaded)."""
    field = start.field
    if field.slice_px is not None:
        why = (
            f"the views' projected mass grows like 1/cos(tilt) ({field.evidence.z:.1f} standard errors, "
            f"{field.evidence.outside_fraction:.0%} of the zero-tilt mass)"
            if option == "auto"
            else "extended-object on"
        )
        CONSOLE.print(
            f"gaussian-atoms: an object wider than the field of view: {why}; Gaussians fill "
            f"{2 * field.reach / length_scale:.0f} Å across the tilt axis, those above the detector are reported as "
            f"atoms"
        )
    if start.weights is not None:
        CONSOLE.print(
            f"gaussian-atoms: {len(start.means)} Gaussians start at back-projection maxima"
            + (" (found while the launcher loaded)" if ahead else "")
        )


def say_series(series) -> None:
    """Say on one line what the run fits: the views (and those left out), their tilts and axis,
    the detector, the pixel size and where it came from, the species."""
    if series is None:
        return
    n, h, w = series.projections.shape
    left_out = np.setdiff1d(np.arange(series.views_given), series.view_indices)
    euler = f", Euler angles {series.euler_convention}" if series.euler_deg is not None else ""
    CONSOLE.print(
        f"gaussian-atoms: {n} views"
        + (f" ({len(left_out)} left out: {', '.join(map(str, left_out[:8]))})" if len(left_out) else "")
        + f", tilts {series.angles_deg.min():g} to {series.angles_deg.max():g}° about {series.tilt_axis}{euler}; "
        f"{h} x {w} pixels of {series.pixel_size_A:g} Å"
        + (f" (from {series.pixel_size_source})" if series.pixel_size_source else "")
        + f"; species {','.join(series.species) if series.species else 'not given'}"
    )


def species_rules(density, species: tuple[str, ...]) -> None:
    """What the elements given set in the density control: the hard core (:func:`say_hard_core`)
    and the least mass a light element's atom can have against a heavy one's
    (:func:`~gaussian_atoms_method.atoms.species.lightest_mass_ratio`)."""
    from gaussian_atoms_method.atoms.species import lightest_mass_ratio

    density.hard_core_A = say_hard_core(species)
    density.lightest_mass_ratio = lightest_mass_ratio(species)


def say_hard_core(species: tuple[str, ...]) -> float | None:
    """Say the material's hard core (:mod:`gaussian_atoms_method.atoms.hard_core`) on one line:
    from ``species`` when given (returned, Å), else that it is read from the atoms (None)."""
    from gaussian_atoms_method.atoms.hard_core import COVALENT_FRACTION, SHELL_FRACTION, hard_core_from_species

    if species:
        distance = hard_core_from_species(species)
        CONSOLE.print(
            f"gaussian-atoms: hard core {distance:.2f} Å ({','.join(species)}: {COVALENT_FRACTION:.2f} of the least "
            f"sum of covalent radii): no two atoms closer"
        )
        return distance
    CONSOLE.print(
        f"gaussian-atoms: hard core read from the confident atoms ({SHELL_FRACTION:.2f} of their first shell's peak; "
        f"give the elements with --species to set it)"
    )
    return None


def noise_after_fit(before: NoiseModel, measured, predicted, sigma_px: float) -> tuple[NoiseModel, float]:
    """The noise the final tests judge in: ``before`` (read before training) scaled by how much
    more the fit's residuals vary over an atom than it says
    (:func:`~gaussian_atoms_method.physics.noise.atom_scale_excess`), never scaled down.  Where
    the data match the forward model the residual is that noise and the factor is about 1; on
    real data (a denoised film, a probe's tails) the fit leaves structure that no Gaussian should
    be kept or split for.  ``measured``, ``predicted``: (V, H, W) arrays, or tensors on one
    device (read there).  Returns the scaled model and the factor."""
    factor = max(atom_scale_excess(measured - predicted, before.variance(predicted), sigma_px), 1.0)
    return inflated(before, factor), factor


def read_after_fit(model) -> None:
    """Before the final merges and prune, from the fit's residual: where the views' spectrum could
    not say how their noise is correlated, read the noise an atom sees from what neighbouring views
    do not share (:func:`views_noise_after_fit`; ``model.measured_noise`` then holds it), and set the
    density control to judge in the noise after the fit (:func:`noise_after_fit`, at the Gaussians'
    median width), saying so when it is larger than the noise read before training."""
    from gaussian_atoms_method.engine.residuals import measured_views, render_training_views

    judge = model.density.noise is not None and model.config.judge_after_fit
    before = getattr(model, "measured_noise", None)
    unread = before is not None and not before.correlation_read
    series = model.view_set.series
    known = before is not None and getattr(series, "noise_path", None) is not None
    if model.num_points == 0 or not (judge or unread or known):
        return
    measured = measured_views(model)
    if measured is None:
        return
    predicted = render_training_views(model, on_device=True)  # read on the model's device
    sigma_px = float(model.sigmas.median()) / model.density.pixel_size
    if unread:
        model.measured_noise = views_noise_after_fit(model, before, measured, predicted, sigma_px)
    if known:
        model.noise_check = check_noise_reading(model, before, predicted, sigma_px)
    if not judge:
        return
    judged, factor = noise_after_fit(model.density.noise, measured, predicted, sigma_px)
    if factor > 1.0:  # standard deviations, as say_residual states the residual
        said = f"{np.sqrt(factor):.3g} times the noise read before training"
        views = model.measured_noise if unread else None
        if views is not None and views.correlation_from == "views" and views.correlation > 1.0:
            said = (
                f"{np.sqrt(factor / views.correlation):.2f} times the noise the views hold there (read from what "
                f"neighbouring views do not share; {said}, from neighbouring pixels)"
            )
        CONSOLE.print(
            f"gaussian-atoms: over an atom the fit's residuals are {said}; the final merges and prune judge in that"
        )
    model.density.noise = judged


def views_noise_after_fit(model, before: NoiseModel, measured, predicted, sigma_px: float) -> NoiseModel:
    """``before`` (read from neighbouring pixels) times the noise an atom sees over it, read from
    what neighbouring views do not share of the (V, H, W) residual ``measured - predicted``
    (:func:`~gaussian_atoms_method.physics.view_disagreement.view_disagreement`), never scaled
    down; said on one line.  ``before`` as it was where the views are too few or too small."""
    read = disagreement(model, before, measured, predicted, sigma_px)
    if read is None:
        return before
    factor = max(read.noise_excess, 1.0)
    sigma_A = sigma_px * model.view_set.series.pixel_size_A
    CONSOLE.print(
        f"gaussian-atoms: the views' noise over an atom, read from what neighbouring views do not share of the "
        f"fit's residual: {factor:.3g} times the variance neighbouring pixels show (correlated noise: denoised or "
        f"filtered views; atoms {sigma_A:.3g} Å wide); {read.structure_share:.0%} of the residual's variance over "
        f"an atom is shared by the views.  A replica with this noise: gaussian-atoms simulate --like DATA "
        f"--noise-over-atom {factor:.3g} --noise-sigma-A {sigma_A:.3g}"
    )
    return replace(inflated(before, factor), correlation=factor, correlation_read=True, correlation_from="views")


def check_noise_reading(model, pixels: NoiseModel, predicted, sigma_px: float) -> dict | None:
    """The run's noise over an atom (``model.measured_noise``'s correlation) against the noise a
    replica drew into its views (the series' ``noise_path``), both in units of the ``pixels``
    reading at the (V, H, W) ``predicted`` levels, at atoms of ``sigma_px``; said on one line,
    returned for ``evaluation.json``.  None (said) where the file does not hold the views."""
    from gaussian_atoms_method.physics.view_disagreement import known_noise_over_atom

    series = model.view_set.series
    noise = np.load(series.noise_path, mmap_mode="r")
    if series.view_indices is not None and len(noise) == (series.views_given or len(noise)):
        noise = noise[np.asarray(series.view_indices)]
    if noise.shape != tuple(predicted.shape):
        CONSOLE.print(
            f"gaussian-atoms: {series.noise_path}: noise of shape {noise.shape}, not the views' "
            f"{tuple(predicted.shape)}; the noise reading is not checked"
        )
        return None
    level = np.clip(predicted.detach().cpu().double().numpy(), 0, None)
    scaled = np.asarray(noise, dtype=np.float64) * model.normalisation.data_scale
    true = known_noise_over_atom(scaled, pixels.pixel_variance(level), sigma_px)
    if true is None:
        return None
    read = float(model.measured_noise.correlation)
    CONSOLE.print(
        f"gaussian-atoms: the noise over an atom read {read:.3g} times what neighbouring pixels show; the noise "
        f"drawn into these views ({series.noise_path.name}) holds {true:.3g} times it there: read / drawn "
        f"{read / true:.3f}"
    )
    return {"noise_over_atom_read": read, "noise_over_atom_drawn": true}


def disagreement(model, pixels: NoiseModel, measured, predicted, sigma_px: float):
    """What neighbouring views do not share of the (V, H, W) residual ``measured - predicted`` over
    an atom of ``sigma_px``, in units of the ``pixels`` noise model's own (its correlation left out;
    :func:`~gaussian_atoms_method.physics.view_disagreement.view_disagreement`), the beams the
    model's views'; None where the views are too few or too small."""
    from gaussian_atoms_method.engine.rendering import detector_axes
    from gaussian_atoms_method.physics.view_disagreement import view_disagreement

    residuals = (measured - predicted).detach().cpu().double().numpy()
    variance = pixels.pixel_variance(np.clip(predicted.detach().cpu().double().numpy(), 0, None))
    axes = detector_axes(model.view_c2w.detach().cpu().double()).numpy()
    beams = np.cross(axes[:, 0], axes[:, 1])  # the beam is normal to the detector's rows and columns
    return view_disagreement(residuals, variance, sigma_px, beams)


def say_residual(
    measured: NoiseModel | None, scale: float, predicted, noise: float, position_factor: float, amplitude_factor: float
) -> None:
    """Say the fit's residual (level ``noise``, input units; its weights at the atoms' scale,
    :func:`~gaussian_atoms_method.atoms.information.residual_spectrum_factors`) against the noise
    ``measured`` before the fit (normalised units, data times ``scale``), both over an atom (its
    matched template; the reading is the atoms' own, :attr:`NoiseModel.correlation`), at the
    (V, H, W) ``predicted`` levels."""
    if measured is None:
        return
    expected = float(np.mean(measured.scaled(1.0 / scale).variance(np.clip(predicted, 0, None))))
    over_atom = (noise * amplitude_factor) ** 2
    structure = (
        f"{max(0.0, 1.0 - expected / over_atom):.0%} of it is structure no atom explains"
        if measured.correlation_read
        else "how much of it is structure is not known (the noise was read from neighbouring pixels only)"
    )
    source = (
        "read from what neighbouring views do not share"
        if measured.correlation_from == "views"
        else "read from them before the fit"
    )
    CONSOLE.print(
        f"gaussian-atoms: residual {noise:.4g} (input units); over an atom {np.sqrt(over_atom / expected):.2f} times "
        f"the noise the views hold there ({source}): {structure}; the evidence weighs it "
        f"{position_factor:.2f} (positions) and {amplitude_factor:.2f} (amplitudes) times white noise of its level"
    )
