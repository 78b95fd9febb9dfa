"""The error a run's stated precision cannot show, read on an internal replica of its own result.

A run states each atom's precision from the scatter its views show. A bias alike in every view (the
atom's profile and the probe's rings against the fit's Gaussians, the views' misregistration spread
over every atom) stays outside that statement, and no fit sees it in its own residual. So the run's
own atoms are taken as a truth and drawn again through physics the fit does not share
(:func:`~gaussian_atoms_method.harness.replica.replica_of`: ADF atoms, a probe from its optics), in
the series' own geometry, level and noise, with a misregistration of the size the run read off its
views or the shifts it learned (:func:`~gaussian_atoms_method.engine.own_floor.registration_of`);
the replica is fitted as the run was, and its errors against those atoms beside the precision its
fit stated give the floor (:func:`~gaussian_atoms_method.atoms.calibration.precision_floor_A`).
Given to the run (``--pipeline.model.precision-floor-A``), it is added in quadrature to each atom's
statement.

The replica's probe is an assumption
(:data:`~gaussian_atoms_method.physics.microscope.DEFAULT_OPTICS` unless given): the floor holds the
bias of that physics, not of the microscope's own, which nothing here knows.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gaussian_atoms_method.atoms.atom_set import AtomSet
from gaussian_atoms_method.engine.own_floor import MATCH_RADIUS_A, registration_of


@dataclass
class InternalFloor:
    """``floor_A`` (3,) the error along x, y, z (Å) the stated intervals did not hold on the
    internal replica; ``coverage_95`` (3,) the share of its errors inside the intervals its fit
    stated; ``found`` the share of the run's atoms the replica's fit found; ``rmsd_pm`` over them;
    ``shifts_rms_px`` (2,) the replica's misregistration (rows, columns); ``offsets_rms_px`` (2,)
    what its fit's views were read to sit off its atoms."""

    floor_A: np.ndarray
    coverage_95: np.ndarray
    found: float
    rmsd_pm: float
    shifts_rms_px: np.ndarray
    offsets_rms_px: np.ndarray


def internal_floor(
    series,
    atoms: AtomSet,
    *,
    species: str | None = None,
    seed: int = 0,
    optics=None,
    support_A: float = 0.0,
    device: str = "auto",
    max_num_iterations: int | None = None,
    **model_options,
) -> InternalFloor:
    """The floor of ``atoms`` (a run's result on ``series``, in its truth frame, as
    :func:`gaussian_atoms_method.reconstruct` returns them) read on an internal replica (module text).

    Parameters
    ----------
    series : TiltSeries
        The series the run fitted.
    atoms : AtomSet
        Its atoms, their ``info`` holding the views' registration (:func:`registration_of`).
        Elements from ``atoms.species`` or ``species`` (one element for all).
    species : str, optional
        The specimen's elements, as the run was given them.
    seed : int
        The replica's draws (misregistration, noise).
    optics : ProbeOptics, optional
        The replica's probe (default :data:`.replica.DEFAULT_OPTICS`).
    support_A : float
        An amorphous carbon support under the atoms this thick, Å (0: none), as the specimen has.
    device, max_num_iterations, **model_options
        As the run: :func:`gaussian_atoms_method.reconstruct`'s.
    """
    import dataclasses

    from gaussian_atoms_method.api import reconstruct
    from gaussian_atoms_method.atoms.calibration import Z95, precision_floor_A
    from gaussian_atoms_method.atoms.matching import shifted_errors
    from gaussian_atoms_method.harness.replica import DEFAULT_OPTICS, replica_of

    elements = atoms.species
    if elements is None or np.any(np.asarray(elements) == "X"):
        if not species or "," in species:
            raise ValueError("the internal floor needs each atom's element: give species (one element)")
        elements = np.full(len(atoms), species)
    origin = np.asarray(series.origin_A, dtype=np.float64)
    truth = AtomSet(atoms.positions - origin, species=np.asarray(elements))
    n_views = len(series.projections)
    shifts, gains = registration_of(atoms.info, n_views, seed)
    made = replica_of(series, truth, seed=seed, shifts_px=shifts, optics=optics or DEFAULT_OPTICS, support_A=support_A)
    projections = (made.projections * gains[:, None, None]).astype(np.float32)
    replica_series = dataclasses.replace(series, projections=projections, truth_path=None, noise_path=None)
    model_options.setdefault("own_floor", False)  # the floor is read here: the refit states the views' scatter
    refit = reconstruct(
        replica_series,
        species=species,
        device=device,
        max_num_iterations=max_num_iterations,
        progress=False,
        seed=seed,
        **model_options,
    )
    refit_offsets = np.asarray(refit.info.get("view_offsets_px", np.zeros((n_views, 2))), dtype=np.float64)
    pred = refit.positions - origin
    pi, ti, error = shifted_errors(pred, truth.positions, MATCH_RADIUS_A)
    stated = refit.position_std_A[pi]
    inside = np.abs(error) <= Z95 * stated
    return InternalFloor(
        floor_A=precision_floor_A(error, stated),
        coverage_95=inside.mean(axis=0) if len(pi) else np.full(3, np.nan),
        found=len(pi) / max(len(truth), 1),
        rmsd_pm=float(np.sqrt((error**2).sum(axis=1).mean()) * 100) if len(pi) else float("nan"),
        shifts_rms_px=np.sqrt((shifts**2).mean(axis=0)),
        offsets_rms_px=np.sqrt((refit_offsets**2).mean(axis=0)),
    )
