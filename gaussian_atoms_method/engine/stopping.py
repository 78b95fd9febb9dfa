"""What a run does at each convergence check (:mod:`.convergence`): stop once the atoms are
settled; until then, search the residuals for missing atoms, apply the final merges and prune
early when only the set still churns, and slow the positions when they only scatter.

The rules: once the positions have settled while the set still churns, the final rules that
do not read the residual run then (:func:`settle_set`; without them Au noise 500 ended with
0.0025 false atoms per atom instead of 0.0004), the merge by likelihood left to the end; once
the positions only scatter, their rate is halved down to the schedule's final rate
(:func:`slow_positions`); a residual search whose additions the prune took back is the last.
"""

from __future__ import annotations

import numpy as np
import torch

from gaussian_atoms_method.atoms.uncertainty import existence_significance
from gaussian_atoms_method.engine.console import CONSOLE
from gaussian_atoms_method.engine.residuals import add_missing_atoms
from gaussian_atoms_method.engine.results import fitted_loss, model_position_std_A, residual_noise

POSITIONS = "means"


def converged(model, step: int) -> bool:
    """True once the atoms are settled (:mod:`gaussian_atoms_method.engine.convergence`): the
    positions against their precision under the residual at the atoms' scale, the set by the
    Gaussians whose existence that residual would prove."""
    check = model.convergence
    if not check.checks(step):
        return False
    atoms = model.atoms()
    levels = {}

    def precision(noise):
        if noise is None:
            read = atom_scale_noise(model, atoms)
            if read is None:
                return None
            noise, levels["amplitude"] = read
        result = model_position_std_A(model, atoms, noise)
        return None if result is None else (*result, levels.get("amplitude"))

    (worth, beyond), core = model.density.field_worths(model.gauss_params), model.density.known_hard_core()
    existence = existence_at_unit_noise(model, atoms)
    return check.update(step, model.means, model.normalisation.length_scale, precision, worth, core, existence, beyond)


@torch.no_grad()
def atom_scale_noise(model, atoms) -> tuple[float, float] | None:
    """The white levels (input units) the fit's residual weighs at the atoms' scale, for a
    position and for an amplitude (:func:`residual_noise` times
    :func:`~gaussian_atoms_method.atoms.information.residual_spectrum_factors` at the atoms'
    median width): the residual that is there, its level and its grain, against which the fit's
    steps and the atoms' existence are judged during training; None without the tilt series."""
    series = model.view_set.series
    read = residual_noise(model) if series is not None and len(atoms) else None
    if read is None:
        return None
    from gaussian_atoms_method.atoms.information import residual_spectrum_factors

    noise, residuals, _ = read
    sigma_px = float(np.median(atoms.sigmas)) / series.pixel_size_A
    position, amplitude = residual_spectrum_factors(residuals / model.normalisation.data_scale, noise, sigma_px)
    return noise * position, noise * amplitude


def existence_at_unit_noise(model, atoms) -> np.ndarray | None:
    """(N,) each Gaussian's existence significance under white noise of one input unit
    (:func:`~gaussian_atoms_method.atoms.uncertainty.existence_significance`); None without the
    tilt series."""
    series = model.view_set.series
    if series is None or len(atoms) == 0:
        return None
    n_views = model.view_c2w.shape[0]
    return existence_significance(atoms.sigmas, atoms.amplitudes, n_views, series.pixel_size_A, 1.0, fitted_loss(model))


def at_check(model, step: int, last_step: int) -> bool:
    """Act on the convergence check after ``step`` (the refine and merge callbacks have run);
    True when the run should stop.  Every run searches the residuals at least once, at the last
    refine before ``stop_split_at``."""
    cfg, density, check = model.config, model.density, model.convergence
    search, last_search = (
        density.residual_check_open(step),
        step == min(density.stop_split_at, last_step) - cfg.refine_every,
    )
    if step >= last_step or not (cfg.stop_when_converged or search):
        return False
    settled = model.converged(step)
    if check.checks(step) and not density.additions_settled(model.gauss_params):
        settled = False  # a search's additions still gaining their mass: the final rules wait for them
    tolerated = check.changed_fraction * model.num_points
    if search and (settled or last_search):
        if settled and density.state.searched_at and density.descendants(density.state.searched_at) <= tolerated:
            density.state.residual_clean = True  # the last search's additions did not survive: searching is over
        elif added := add_missing_atoms(model):
            model.atoms_changed()
            density.state.residual_clean = settled and added <= tolerated
            density.state.searched_at, density.state.settled_since_search = step, False
            return False
    # a run told to train on keeps its schedule and its set
    if settled or not cfg.stop_when_converged or not check.checks(step):
        return settled and cfg.stop_when_converged
    if check.positions_settled >= 2 and check.churning >= 2 and not density.state.settled_since_search:
        CONSOLE.print(
            f"gaussian-atoms: step {step}: the positions have settled but the set has not: the merge of unresolved "
            f"pairs and the final prune removed {settle_set(model)} Gaussians (the merge by likelihood waits for the "
            f"end)"
        )
    elif check.scatter_only and not check.positions_settled and slow_positions(model):
        CONSOLE.print(f"gaussian-atoms: step {step}: the positions only scatter: their learning rate is halved")
    return False


def settle_set(model) -> int:
    """Apply the final rules that do not read the residual now (the merge of pairs the data
    cannot resolve, the final prune, the distance merge:
    :meth:`~gaussian_atoms_method.density.strategy.DensityControl.settle` without correlations)
    and compare the next check with what is left; returns how many Gaussians went.  The merge by
    likelihood waits for the end: its test holds where the residual is noise, at a converged fit."""
    removed = model.density.settle(model.gauss_params, model.optimizers, model._param_lists())
    model.density.state.settled_since_search = True
    worth, beyond = model.density.field_worths(model.gauss_params)
    model.convergence.restart(model.means, worth, existence_at_unit_noise(model, model.atoms()), beyond)
    if removed:
        model.atoms_changed()
    return removed


def set_position_rate(model, optimizers) -> bool:
    """Rescale the positions' learning rate (their optimiser's rate and its scheduler's base) to
    ``position_rate_px`` detector pixels, once per optimiser (the mark travels in its state dict:
    a resumed run is not rescaled twice).  Returns whether it was rescaled."""
    rate_px, pixel_A = model.config.position_rate_px, model.view_set.pixel_size_A
    optimizer = getattr(optimizers, "optimizers", {}).get(POSITIONS)
    if rate_px is None or not pixel_A or optimizer is None or optimizer.param_groups[0].get("rate_px"):
        return False
    group = optimizer.param_groups[0]
    _scale_rate(
        optimizers,
        rate_px * pixel_A * model.normalisation.length_scale / group.get("initial_lr", group["lr"]),
        rate_px=rate_px,
    )
    return True


def slow_positions(model) -> bool:
    """Halve the positions' learning rate (their optimiser's rate and its scheduler's base),
    unless that would take it below the schedule's final rate; a rate without a scheduler is the
    user's constant and stays.  Returns whether it was halved."""
    optimizers = model._optimizers_obj
    scheduler = getattr(optimizers, "schedulers", {}).get(POSITIONS)
    if scheduler is None or not hasattr(scheduler, "lr_lambdas"):
        return False
    group = optimizers.optimizers[POSITIONS].param_groups[0]
    final = group.get("initial_lr", group["lr"]) / group.get("rate_factor", 1.0) * scheduler.lr_lambdas[0](10**9)
    if group["lr"] * 0.5 < final:
        return False
    _scale_rate(optimizers, 0.5, rate_factor=group.get("rate_factor", 1.0) * 0.5)
    return True


def _scale_rate(optimizers, factor: float, **marks) -> None:
    """Scale the positions' learning rate by ``factor``: their optimiser's rate, the base its
    scheduler scales (``initial_lr`` and ``base_lrs``), and set ``marks`` on its parameter groups
    (they travel in the optimiser's state dict, so a resumed run keeps them)."""
    for g in optimizers.optimizers[POSITIONS].param_groups:
        g["lr"] *= factor
        if "initial_lr" in g:
            g["initial_lr"] *= factor
        g.update(marks)
    scheduler = optimizers.schedulers.get(POSITIONS)
    if scheduler is not None and hasattr(scheduler, "base_lrs"):
        scheduler.base_lrs = [b * factor for b in scheduler.base_lrs]
