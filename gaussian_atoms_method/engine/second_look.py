"""A second look: the fit starts again from its Gaussians and every place an atom could be where
the residuals hold positive mass, and that fit's atoms are the run's.

A light atom beside its bonded neighbours can be lost for good.  Early in the fit one Gaussian
settles between two atoms with one atom's mass and its neighbours take up the rest, so the
residual the missed atom leaves is weak (on carbon phase images at 2,000 e/Å² a median 2.0 noise
standard deviations in the residuals' back-projection), under any level a search for findings
must keep (:func:`~gaussian_atoms_method.atoms.residual_sites.unexplained_sites`); and a Gaussian
added there late, with that peak's small mass, cannot win the mass back from neighbours that
have settled.  Started again from the schedule's beginning, every Gaussian on an equal footing,
the fit judges each place itself.  So once the fit has converged, a Gaussian is proposed at every
open place (inside the material, at least the hard core from every Gaussian) where the residuals'
smoothed back-projection has a local maximum of positive mass
(:func:`~gaussian_atoms_method.atoms.residual_sites.open_place_peaks`), and the fit starts again
from its Gaussians and the proposals, as from ``start_atoms``.

Once a run, only where the hard core is known (``--species``, or read from the confident atoms),
and only where the places hold evidence of missing atoms (:func:`proven_places`): the residuals
prove more than half an atom, its neighbours re-fitted, at more places than they prove less than
minus half a one (:mod:`~gaussian_atoms_method.atoms.proposal_test`, at the evidence's proof
level), by more than the convergence tolerates as a change of the set and by the proof level
times that excess's Poisson standard error.  Every open place is proposed, not the proven ones
alone: a missed atom's place often proves less than half an atom while its neighbours hold its
mass (7,000 carbon atoms: 0.975 found proposing the 355 proven places, 0.994 all 771).  A
full second fit with hundreds of proposals where none was missing made a 2,000-atom Ni-Pd-Pt
particle worse (1.000 -> 0.994 found, 0.0015 -> 0.010 false, on 3 proven places): the gate
keeps it from such runs.

Measured on 7,000 carbon atoms in phase images at 2,000 e/Å² (this CPU, ``ga.reconstruct(...,
species="C")``): found 0.931 -> 0.994, 0.0039 -> 0.0020 false per atom, 22.4 -> 16.8 pm (the
same fit started again from its own atoms alone: 0.945; from them and the 475 missed true atoms:
0.990).
"""

from __future__ import annotations

import numpy as np
import torch

from gaussian_atoms_method.atoms.atom_set import read_atoms
from gaussian_atoms_method.atoms.evidence import proof_level
from gaussian_atoms_method.atoms.information import residual_spectrum_factors
from gaussian_atoms_method.atoms.proposal_test import proposal_significance
from gaussian_atoms_method.atoms.residual_sites import open_place_peaks
from gaussian_atoms_method.engine.console import CONSOLE
from gaussian_atoms_method.engine.rendering import detector_axes
from gaussian_atoms_method.engine.residuals import render_training_views
from gaussian_atoms_method.physics.noise import mad_std


def start_positions(model) -> np.ndarray | None:
    """(N, 3) Å about the tilt centre where the fit's Gaussians start: a second look's (the
    Gaussians and the proposals), else ``start_atoms``' atoms (read in the frame ``atoms.xyz``
    is written in: the series' ``origin_A`` at the tilt centre), else None (the start's own
    search)."""
    again = getattr(model, "second_look_start", None)
    if again is not None:
        return again
    path = model.config.start_atoms
    if path is None:
        return None
    return read_atoms(path).positions - np.asarray(model.normalisation.origin_A, dtype=np.float64)


def look_again(model, step: int) -> bool:
    """At the fit's first convergence, with ``second_look`` on: the proposals (module docstring);
    where the data prove more of them than the convergence tolerates as a change of the set,
    note the start of the fit again (``model.second_look_start``), say so and return True (the
    pass ends without results; :meth:`~.fit.AtomFit.start_again` starts the next).  False where
    the run ends here."""
    if not model.config.second_look or getattr(model, "second_look_start", None) is not None:
        return False
    series, projections = model.view_set.series, model.view_set.projections
    ls = model.normalisation.length_scale
    hard_core = model.density.hard_core(model.gauss_params) / ls  # Å; infinite where unknown
    if series is None or projections is None or model.num_points == 0 or not np.isfinite(hard_core):
        return False
    with torch.no_grad():
        predicted = render_training_views(model)
        residuals = (np.asarray(projections, dtype=np.float64) - predicted) / model.normalisation.data_scale
        inside = model.density.in_field(model.means.detach()).cpu().numpy()
        existing = model.means.detach().cpu().double().numpy()[inside] / ls  # Å about the tilt centre
        atoms = model.atoms()  # widths in Å, amplitudes in the input's units
    places = open_place_peaks(
        residuals.astype(np.float32), series.angles_deg, series.pixel_size_A, existing, hard_core, series.tilt_axis,
        series.centre_px, tilt_axis_angle_deg=series.tilt_axis_angle_deg, device=str(model.means.device),
    )  # fmt: skip
    tolerated = model.convergence.changed_fraction * model.num_points
    if len(places) <= tolerated:  # not even every place proven would be more than the set may change
        return False
    proven, against = proven_places(model, places, existing, atoms.sigmas[inside], atoms.amplitudes[inside], residuals)
    excess = int(proven.sum()) - int(against.sum())
    if excess <= tolerated:
        return False
    if excess < proof_level(len(existing)) * np.sqrt(proven.sum() + against.sum()):
        return False
    model.second_look_start = np.vstack([existing, places])  # the model's frame, as start_atoms are read
    model.second_look_pending = True
    CONSOLE.print(
        f"gaussian-atoms: step {step}: converged; a second look: of the {len(places)} places an atom could be (at "
        f"least the hard core {hard_core:.2f} Å from every Gaussian) with positive mass there, the residuals prove "
        f"more than half an atom at {int(proven.sum())} and less than minus half a one at {int(against.sum())}, "
        f"its neighbours re-fitted: the fit starts again from its {len(existing)} Gaussians and all {len(places)} "
        f"places"
    )
    return True


def proven_places(model, places: np.ndarray, positions_A, sigmas_A, amplitudes, residuals: np.ndarray) -> tuple:
    """Two (M,) bool: where at ``places`` (Å about the tilt centre) the ``residuals`` (V, H, W,
    input units) prove more than half an atom with its neighbours re-fitted, and where less than
    minus half a one (:func:`~gaussian_atoms_method.atoms.proposal_test.proposal_significance`,
    at the evidence's proof level, for the Gaussians at ``positions_A``, Å about the tilt centre,
    with ``sigmas_A`` and ``amplitudes``).  The second is the null's: a fit's misfit, not a
    missing atom, can ask for either sign.  Proven, against: carbon missing 475 atoms 449 and 17
    of 779 places (271 proven within 0.75 Å of a missed atom); an 11 Å Au particle found whole 0
    and 61 of 1,660; the aSi-208 counts at each dose none either way (without the half atom: 53,
    25 and 7 proven)."""
    if len(places) == 0:
        return np.zeros(0, bool), np.zeros(0, bool)
    series = model.view_set.series
    noise = mad_std(residuals)
    _, amplitude_factor = residual_spectrum_factors(residuals, noise, float(np.median(sigmas_A)) / series.pixel_size_A)
    axes = detector_axes(model.view_c2w.cpu().double()).numpy()
    z, whole = proposal_significance(
        places, positions_A, sigmas_A, amplitudes, axes, residuals, series.pixel_size_A, series.centre_px, noise,
        amplitude_factor,
    )  # fmt: skip
    level = proof_level(len(positions_A))
    return z - 0.5 * whole >= level, z + 0.5 * whole <= -level
