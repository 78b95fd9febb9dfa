"""What a run leaves in its directory: the atoms with their precision, a slices figure, the
scores against a truth file, and snapshots during training.

* ``atoms.xyz`` / ``atoms.csv``: the final Gaussians that are atoms, in Å (after the last merge
  and prune), with each position's Cramér-Rao precision; ``non_atoms.xyz``: the rest (beyond the
  field of view, or outside the support); ``classes.png``: their population by class;
* ``slices.png``: central slices of the potential with the atoms (and the true ones);
* ``evaluation.json``: TPR, false positives per true atom and RMSD, with a truth file;
* ``snapshots/step-NNNNNN.csv`` and ``snapshots/times.csv``: with ``snapshot_every``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path

import numpy as np
import torch

from gaussian_atoms_method.atoms import picture_process
from gaussian_atoms_method.atoms.atom_set import AtomSet, read_atoms, write_atoms
from gaussian_atoms_method.atoms.calibration import wider_than_one_atom
from gaussian_atoms_method.atoms.classification import classify_gaussians, in_support
from gaussian_atoms_method.atoms.evidence import EVIDENCE_SCORES
from gaussian_atoms_method.atoms.hard_core import most_apart
from gaussian_atoms_method.atoms.matching import score_atoms, uncount_straddling
from gaussian_atoms_method.atoms.pictures import draw_slices, write_population_png, write_rdf_png
from gaussian_atoms_method.atoms.slices import slice_planes
from gaussian_atoms_method.atoms.structure_evidence import structure_evidence
from gaussian_atoms_method.atoms.trust import depth_unlike_its_element, mass_unlike_one_atom, open_atoms
from gaussian_atoms_method.atoms.uncertainty import position_std_A, robust_noise_std
from gaussian_atoms_method.engine.console import CONSOLE
from gaussian_atoms_method.engine.noise_reading import say_residual
from gaussian_atoms_method.engine.own_floor import widen_by_own_floor
from gaussian_atoms_method.engine.progress import ProgressBar
from gaussian_atoms_method.engine.rendering import detector_axes
from gaussian_atoms_method.engine.residuals import (
    measured_views,
    render_training_views,
    say_view_shifts,
    write_learned_registration,
)
from gaussian_atoms_method.physics.noise import fit_noise_model


@torch.no_grad()
def residual_noise(model) -> tuple[float, torch.Tensor, torch.Tensor] | None:
    """The pixel noise of the fit's residuals over the training views (robust standard
    deviation, input units), with the residuals and the predicted projections (V, H, W) in
    normalised data units (``model.normalisation.data_scale`` per input unit), tensors on the
    model's device (the noise readings run there); None without the tilt series."""
    measured = measured_views(model)
    predicted = render_training_views(model, on_device=True) if measured is not None else None
    if predicted is None:
        return None
    residuals = predicted - measured
    return robust_noise_std(residuals) / model.normalisation.data_scale, residuals, predicted


@torch.no_grad()
def model_position_std_A(model, atoms: AtomSet, noise: float | None = None) -> tuple[np.ndarray, float] | None:
    """Each atom's position precision (N, 3) in Å and the pixel noise it assumes (input units;
    estimated from the residuals of the training views unless given, :func:`residual_noise`)
    (:mod:`gaussian_atoms_method.atoms.uncertainty`); None without the tilt series (a model
    built outside the dataparser)."""
    series, projections = model.view_set.series, model.view_set.projections
    if series is None or projections is None or len(atoms) == 0:
        return None
    if noise is None:
        noise = residual_noise(model)[0]
    axes = detector_axes(model.view_c2w.cpu().double()).numpy()  # the training views' detectors
    return position_std_A(atoms.sigmas, atoms.amplitudes, axes, series.pixel_size_A, noise, fitted_loss(model)), noise


def fitted_loss(model) -> str:
    """The estimator the positions were fitted with, as the bounds take it: ``"l1"`` for the L1
    data term, else ``"l2"`` (the Poisson term is a weighted least-squares fit, at the pixels'
    mean noise; Huber's is within 5% of it, ``HUBER_EFFICIENCY``)."""
    return "l1" if model.data_term == "l1" else "l2"


def write_results(model, run_dir: Path) -> dict | None:
    """After the model's last merge and prune, write ``atoms.xyz``, ``atoms.csv`` (with each
    atom's position precision), ``slices.png`` and, with a truth file, ``evaluation.json``;
    return the scores (None without a truth file).  The pictures are drawn by child processes
    started here, beside the final stage, where there are cores to spare
    (:mod:`~gaussian_atoms_method.atoms.picture_process`)."""
    drawers = picture_process.start(picture_process.RUN_PICTURES)
    try:
        return _write_results(model, run_dir, drawers)
    finally:
        for drawer in drawers or ():
            drawer.close()


def _write_results(model, run_dir: Path, drawers) -> dict | None:
    converged_at = getattr(model, "converged_at", None)
    if converged_at is None and model.config.stop_when_converged:
        CONSOLE.print(
            f"gaussian-atoms: [bold]stopped at the step limit ({model.step + 1} steps) before the atoms "
            f"converged[/bold] ({model.convergence.summary()}): they may still move by more than their stated "
            f"precision; give more steps (--max-num-iterations)"
        )
    model.finalize()
    for line in model.density.report():
        CONSOLE.print(f"gaussian-atoms: {line}")
    if "psf" in model.view_params:
        from gaussian_atoms_method.physics.psf import KERNEL_WIDTHS_A

        fractions = model.view_params["psf"].detach().cpu().clamp(min=0.0).tolist()
        weights = ", ".join(f"{w:.3f} at {s:g} Å" for w, s in zip(fractions, KERNEL_WIDTHS_A))
        CONSOLE.print(
            f"gaussian-atoms: point-spread function ({model.config.psf}): intensity fractions {weights} (the rest in "
            f"the atoms' own widths)"
        )
        # hold it in a later run: --pipeline.model.psf fixed --pipeline.model.psf-weights ...
        run_dir.mkdir(parents=True, exist_ok=True)
        (run_dir / "psf.json").write_text(
            json.dumps(
                {
                    "psf": model.config.psf,
                    "widths_A": list(KERNEL_WIDTHS_A),
                    "intensity_fractions": [round(w, 4) for w in fractions],
                }
            )
            + "\n"
        )
    registration = write_learned_registration(model, run_dir)
    atoms = model.atoms()
    read = residual_noise(model) if len(atoms) else None
    if read is not None:
        # the final residuals' variance-mean relation (input units), read here only: the checks need the level alone
        scale = model.normalisation.data_scale
        model.noise_model = fit_noise_model(read[1] / scale, read[2] / scale)
    precision = model_position_std_A(model, atoms, read[0] if read is not None else None)
    # atoms() lists the Gaussians in the model's order: the density control's own test of the field
    hard_core_A = model.density.hard_core(model.gauss_params) / model.normalisation.length_scale
    if precision is not None:
        atoms.position_std_A, noise = precision
        nm = getattr(model, "noise_model", None)
        if nm is not None:
            CONSOLE.print(
                f"gaussian-atoms: residual noise is {nm.kind}: variance {nm.read_var:.4g} + {nm.gain:.4g} x signal "
                f"(input units; slope {nm.gain_se:.2g} standard error)"
            )
        if model.config.evidence:
            attach_evidence(model, atoms, noise, read, hard_core_A, converged_at is not None)
    in_field = model.density.in_field(model.means.detach()).cpu().numpy()
    beyond_A = atoms.positions[~in_field]  # for the truth's scores: an atom the run placed just beyond the field
    atoms, non_atoms, population, reported = split_atoms(atoms, in_field, model.means.device, hard_core_A)
    series = model.view_set.series
    if series is not None and series.species and len(atoms):
        atoms.species, atoms.element_confidence = name_species(atoms.masses, series.species)
    if atoms.width_std_A is not None:  # after the species: each element's width is its own reference
        level = atoms.info["proof_level"]
        atoms.width_open = wider_than_one_atom(atoms.sigmas, atoms.width_std_A, level, atoms.species)
        atoms.mass_open = mass_unlike_one_atom(atoms.masses, level, atoms.species)
    if model.config.own_floor and not any(model.config.precision_floor_A) and atoms.proven is not None and len(atoms):
        widen_by_own_floor(model, atoms, reported, hard_core_A, read[1], read[0], registration)
    if atoms.width_std_A is not None:  # after the floor: the rise is read in its unit
        floor_z = atoms.info.get("precision_floor_A", model.config.precision_floor_A)[2]
        atoms.depth_open = np.asarray(atoms.depth_open, bool) | depth_unlike_its_element(
            atoms.depth_rise, atoms.info["proof_level"], atoms.species, atoms.depth_halfwidth_A, floor_z
        )
    if atoms.proven is not None:  # after the floor, which may open an atom in depth
        atoms.trusted = ~open_atoms(atoms)
    # Each picture goes to a child as soon as its arrays are known (drawn there while this process
    # writes the atoms); without children, the atoms are written first and the pictures after them.
    pictures = [] if population is None else [(write_population_png, *population, run_dir / "classes.png")]
    _hand_over(pictures, drawers)
    say_evidence(atoms)
    steps = (converged_at if converged_at is not None else model.step) + 1
    model.report = Report(atoms, non_atoms, registration, steps, converged_at is not None)
    write_atoms(atoms, run_dir / "atoms.xyz")
    write_atoms(atoms, run_dir / "atoms.csv")
    write_atoms(non_atoms, run_dir / "non_atoms.xyz")
    evidence, r_A, g = structure_evidence(atoms.positions, hard_core_A)
    (run_dir / "structure.json").write_text(json.dumps(evidence, indent=2) + "\n")
    say_structure(evidence)
    pictures.append(
        (write_rdf_png, r_A, g, evidence["hard_core_A"], evidence["share_under_hard_core"], run_dir / "rdf.png")
    )
    CONSOLE.print(
        f"[bold]gaussian-atoms[/bold]: wrote {len(atoms)} atoms to {run_dir / 'atoms.xyz'} and {len(non_atoms)} "
        f"non-atoms to non_atoms.xyz"
        if model.kept
        else f"[bold]gaussian-atoms[/bold]: {len(atoms)} atoms and {len(non_atoms)} non-atoms returned (no files "
        f"kept: give output_dir to keep the run)"
    )
    truth = read_atoms(model.truth_path) if model.truth_path is not None else None
    covered = counted_truth(model, truth.positions, atoms.positions, beyond_A) if truth is not None else None
    scores = score_atoms(atoms.positions, truth.positions, true_counted=covered) if truth is not None else None
    if scores is not None and atoms.proven is not None and len(atoms):
        from gaussian_atoms_method.atoms.evidence import evidence_scores

        scores |= evidence_scores(atoms, truth, truth_counted=covered)
    if scores is not None:
        scores |= (model.noise_check or {}) | {"converged": converged_at is not None, "steps": steps}
        (run_dir / "evaluation.json").write_text(json.dumps(scores, indent=2) + "\n")
    if len(atoms):
        title = f"{len(atoms)} atoms" + (
            f"; against the truth: TPR {scores['tpr']:.4f}, FP/atom {scores['fp_per_true_atom']:.4f}, RMSD "
            f"{scores['rmsd_pm']:.1f} pm"
            if scores
            else ""
        )
        pictures.append(
            (draw_slices, slice_planes(atoms, truth, device=model.means.device), run_dir / "slices.png", title)
        )
    _hand_over(pictures, drawers)
    for drawer in drawers or ():
        if drawer.picture is not None and not drawer.wait():
            CONSOLE.print(
                f"gaussian-atoms: the child process of {drawer.picture[0].__name__} failed ({drawer.error}); the "
                f"picture is drawn in this one"
            )
            pictures.append(drawer.picture)
    for function, *args in pictures:  # those no child took, or whose child failed: drawn here
        function(*args)
    if scores is None:
        return None
    evidence = {k: scores[k] for k in EVIDENCE_SCORES if k in scores}
    if evidence:
        CONSOLE.print(f"gaussian-atoms: the evidence against {model.truth_path}: {json.dumps(evidence)}")
    plain = {k: v for k, v in scores.items() if k not in evidence}
    CONSOLE.print(f"[bold]gaussian-atoms[/bold]: against {model.truth_path}: {json.dumps(plain)}")
    return scores


def truth_in_field(model, truth_A: np.ndarray) -> np.ndarray:
    """(M,) bool: the true atoms (Å, the truth's frame) inside the field the run reports
    (:meth:`~gaussian_atoms_method.density.strategy.DensityControl.in_field`): a truth wider
    than it (a film's whole model against one sub-area) is scored there only, as the run's own
    atoms are (against the whole 8,284-atom Ta model a sub-area read a TPR of 0.09)."""
    means = torch.as_tensor(model.normalisation.positions_from_A(truth_A), device=model.means.device)
    return model.density.in_field(means.to(model.means.dtype)).cpu().numpy()


def counted_truth(model, truth_A: np.ndarray, reported_A: np.ndarray, beyond_A: np.ndarray) -> np.ndarray:
    """(M,) bool: the true atoms ``truth_A`` a run's scores count, its own ``evaluation.json`` and
    ``check-precision`` alike: those inside its field (:func:`truth_in_field`), less those whose
    one-to-one partner among its ``reported_A`` atoms and the Gaussians it placed beyond the
    field ``beyond_A`` lies beyond it
    (:func:`~gaussian_atoms_method.atoms.matching.uncount_straddling`)."""
    return uncount_straddling(truth_A, truth_in_field(model, truth_A), reported_A, beyond_A)


@dataclasses.dataclass(frozen=True)
class Report:
    """What a run reports as it writes it (:func:`write_results`): ``atoms`` (atoms.xyz), ``non_atoms``
    (non_atoms.xyz), the views' learned ``registration`` ((V, 2) px shifts, (V,) gains) or None,
    the ``steps`` it took and whether it ``converged`` before the step limit."""

    atoms: AtomSet
    non_atoms: AtomSet
    registration: tuple[np.ndarray, np.ndarray] | None = None
    steps: int | None = None
    converged: bool | None = None


def attach_evidence(model, atoms: AtomSet, noise: float, read, hard_core_A: float, converged: bool) -> None:
    """Each of the model's Gaussians ``atoms`` with its evidence
    (:func:`gaussian_atoms_method.atoms.evidence.atom_evidence`): ``significance``, ``proven``,
    ``depth_halfwidth_A``, ``depth_open`` and ``position_std_A`` (neighbours re-fitted, at the
    residual's level and spectrum ``read`` (:func:`residual_noise`), ``noise`` in input units);
    prints what the residual holds beyond the views' own noise and the precision against the
    isolated atom's Cramér-Rao bound (the ``position_std_A`` it replaces)."""
    from gaussian_atoms_method.atoms.calibration import with_floor
    from gaussian_atoms_method.atoms.depth_profile import depth_profile_pulls
    from gaussian_atoms_method.atoms.evidence import atom_evidence
    from gaussian_atoms_method.atoms.information import DetectorField, residual_spectrum_factors, view_scores
    from gaussian_atoms_method.atoms.population import reported_population

    series = model.view_set.series
    scale = model.normalisation.data_scale
    # measured minus predicted (residual_noise holds predicted minus measured), input units; left
    # where the fit ran: the views' pulls and the spectrum read it there
    residuals, predicted = (-read[1] / scale).double(), (read[2] / scale).cpu().numpy()
    sigma_px = float(np.median(atoms.sigmas)) / series.pixel_size_A
    position_factor, amplitude_factor = residual_spectrum_factors(residuals, noise, sigma_px)
    axes = detector_axes(model.view_c2w.cpu().double()).numpy()
    loss = "l1" if model.data_term == "l1" else "l2"
    about_centre = atoms.positions - np.asarray(series.origin_A)
    pulls_args = (about_centre, atoms.sigmas, atoms.amplitudes, axes, residuals, series.pixel_size_A, series.centre_px)
    pulls = view_scores(*pulls_args)
    field = DetectorField.of_views(residuals.shape[-2:], series.pixel_size_A, series.centre_px, series.origin_A)
    in_field = model.density.in_field(model.means.detach()).cpu().numpy()  # those a report may hold
    hard_core = hard_core_A if np.isfinite(hard_core_A) else None
    moved = depth_profile_pulls(*pulls_args, hard_core) if hard_core is not None else None
    bar = ProgressBar(len(atoms), unit="atom", what="gaussian-atoms: evidence") if model.progress else None
    population = reported_population(atoms.sigmas, atoms.amplitudes, in_field)
    evidence = atom_evidence(
        atoms.positions,
        atoms.sigmas,
        atoms.amplitudes,
        axes,
        series.pixel_size_A,
        noise,
        hard_core,
        loss,
        position_factor,
        amplitude_factor,
        pulls,
        in_field,
        moved_pulls=moved,
        progress=None if bar is None else bar.add,
        field=field if field.cuts(axes, atoms.positions, atoms.sigmas) else None,
        population=population,
    )
    if bar is not None:
        bar.close()
    crb = atoms.position_std_A
    floor = model.config.precision_floor_A
    std, half, depth_open = evidence.position_std_A, evidence.depth_halfwidth_A, evidence.depth_open
    rise = evidence.depth_rise
    if any(floor):  # a replica's floor: what no view's scatter shows (atoms/calibration.py)
        std, half, depth_open = with_floor(std, half, depth_open, floor, hard_core, rise)
    atoms.position_std_A, atoms.depth_rise = std, rise
    atoms.significance, atoms.proven = evidence.significance, evidence.proven
    atoms.depth_halfwidth_A, atoms.depth_open = half, depth_open
    atoms.width_std_A, atoms.info["proof_level"] = evidence.width_std_A, evidence.proof_level
    atoms.log_mass_std = evidence.log_mass_std
    say_residual(getattr(model, "measured_noise", None), scale, predicted, noise, position_factor, amplitude_factor)
    atoms.info.update(say_view_shifts(residuals, predicted, axes, model.config.refine_alignment))
    ratio = np.nanmedian(evidence.position_std_A / np.maximum(crb, 1e-12), axis=0)
    CONSOLE.print(
        "gaussian-atoms: median position precision, neighbours re-fitted, from the views' own residuals: "
        + ", ".join(f"{a} {v * 100:.1f} pm" for a, v in zip("xyz", np.nanmedian(evidence.position_std_A, axis=0)))
        + " ("
        + "/".join(f"{r:.2f}" for r in ratio)
        + " times the isolated atom's Cramér-Rao bound"
        + ("" if converged else "; the run did not converge, its errors may be far larger")
        + ")"
        + (
            "; with the floor given, "
            + "/".join(f"{f * 100:.1f}" for f in floor)
            + " pm in quadrature: "
            + ", ".join(f"{a} {v * 100:.1f} pm" for a, v in zip("xyz", np.nanmedian(std, axis=0)))
            if any(floor)
            else ""
        )
    )


def say_evidence(atoms: AtomSet) -> None:
    """The summary line of the reported ``atoms``' evidence: how many to trust and how many each
    reason leaves open (:func:`~gaussian_atoms_method.atoms.trust.trust_words`)."""
    from gaussian_atoms_method.atoms.trust import trust_words

    if atoms.proven is None or not len(atoms):
        return
    CONSOLE.print(f"gaussian-atoms: evidence: {trust_words(atoms)}")


def name_species(masses: np.ndarray, elements: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """The (N,) element of each reported atom of integrated masses ``masses``, from the series'
    ``elements``, and its probability: every atom the one element given, or by mass, heavier
    element for the heavier population (:func:`gaussian_atoms_method.atoms.species.classify_species`);
    prints the counts, and says so where the masses hold fewer populations than elements (then
    every atom is the heaviest element given, its probability NaN)."""
    from gaussian_atoms_method.atoms.species import classify_species, one_population_note, open_elements_words

    species, report = classify_species(masses, list(elements))
    counts = ", ".join(f"{n} {element}" for element, n in report["counts"].items())
    if report.get("separated", True):
        how = f", by mass ({report['test']})" if "test" in report else ""
        CONSOLE.print(f"gaussian-atoms: species {counts}{how}{open_elements_words(report['confidence'])}")
    else:
        CONSOLE.print(one_population_note(report, species[0]))
    return species, report["confidence"]


def _hand_over(pictures: list, drawers) -> None:
    """Give the ``pictures`` ((a function of :mod:`~gaussian_atoms_method.atoms.pictures`,
    *its arguments)) to the ``drawers`` that have none yet, one each; those taken leave the list."""
    for drawer in drawers or ():
        if pictures and drawer.picture is None and drawer.draw(*pictures[0]):
            pictures.pop(0)


def say_structure(evidence: dict) -> None:
    """One line of :func:`~gaussian_atoms_method.atoms.structure_evidence.structure_evidence`."""
    parts = [f"number density {evidence['number_density_per_A3']:.4f} atoms/Å³"]
    if evidence["nearest_neighbour_median_A"] is not None:
        parts.append(f"median nearest neighbour {evidence['nearest_neighbour_median_A']:.2f} Å")
    if evidence["first_shell_peak_A"] is not None:
        parts.append(f"first shell at {evidence['first_shell_peak_A']:.2f} Å")
    if evidence["hard_core_A"] is not None:
        parts.append(
            f"{evidence['share_under_hard_core']:.1%} of atoms closer than the hard core {evidence['hard_core_A']:.2f} "
            f"Å"
        )
    CONSOLE.print("gaussian-atoms: structure: " + ", ".join(parts) + " (rdf.png, structure.json)")


def split_atoms(gaussians: AtomSet, in_field: np.ndarray, device="cpu", hard_core_A: float = math.inf):
    """The Gaussians as atoms and non-atoms: beyond the field of view, or in the field but
    outside the support or in a class apart from the atoms
    (:func:`gaussian_atoms_method.atoms.classification.classify_gaussians`), or within
    ``hard_core_A`` of one the report holds: two atoms never come that close, so of Gaussians
    joined by such pairs it holds those apart that carry the most mass
    (:func:`gaussian_atoms_method.atoms.hard_core.most_apart`; of a pair, the heavier);
    prints the counts (atoms per class).  Returns the atoms, the non-atoms and the population's
    picture's arguments but its path (:func:`gaussian_atoms_method.atoms.pictures.write_population_png`;
    None with no Gaussian in the field) and which Gaussians are the atoms ((N,) bool).  The
    classes' mixture is fitted on ``device`` (the run's)."""
    field = gaussians.subset(in_field)
    classes = classify_gaussians(field.masses, field.sigmas, field.positions, device=device)
    reported = reported_as_atoms(gaussians.positions, in_field, classes.atoms)
    close = np.zeros(len(gaussians), dtype=bool)
    close[reported] = ~most_apart(gaussians.positions[reported], hard_core_A, gaussians.masses[reported])
    reported &= ~close
    labels = np.zeros(len(gaussians), dtype=np.int64)  # 0: a non-atom
    labels[np.flatnonzero(in_field)] = np.where(reported[in_field], classes.classes, 0)
    gaussians = dataclasses.replace(gaussians, info=dict(gaussians.info), atom_class=labels)
    outside, beyond, n_close = int((~classes.atoms).sum()), int((~in_field).sum()), int(close.sum())
    counts = {
        f"class {k}": int(np.sum(reported[in_field] & (classes.classes == k)))
        for k in range(1, len(classes.class_means) + 1)
    }
    counts = {name: n for name, n in counts.items() if n}  # a class reported whole as non-atoms is not listed
    per_class = ", ".join(f"{v} in {k}" for k, v in counts.items()) if len(counts) > 1 else ""
    CONSOLE.print(
        f"gaussian-atoms: {int(reported.sum())} atoms{f' ({per_class}, by mass and width)' if per_class else ''}; "
        f"{outside + beyond + n_close} non-atoms: {outside} outside the atoms' support (no neighbour within the "
        f"material's distances, or a class apart from them), "
        f"{n_close} within the hard core of the atoms reported (the most mass it holds apart), {beyond} beyond the "
        f"field of view"
    )
    others = gaussians.subset(~in_field)

    population = (
        (
            field.masses,
            field.sigmas,
            reported[in_field],
            classes.classes,
            len(classes.class_means),
            (others.masses, others.sigmas),
        )
        if len(field)
        else None
    )
    return gaussians.subset(reported), gaussians.subset(~reported), population, reported


def reported_as_atoms(positions_A: np.ndarray, in_field: np.ndarray, support: np.ndarray | None = None) -> np.ndarray:
    """(N,) bool: the Gaussians a run reports as atoms: in the field of view and, among those,
    in the support (``support``, one per Gaussian in the field, if already known, e.g. from
    :func:`gaussian_atoms_method.atoms.classification.classify_gaussians`; else
    :func:`gaussian_atoms_method.atoms.classification.in_support` of their positions)."""
    reported = np.zeros(len(in_field), dtype=bool)
    reported[np.flatnonzero(in_field)] = in_support(np.asarray(positions_A)[in_field]) if support is None else support
    return reported


def write_snapshot(
    atoms: AtomSet,
    directory: Path,
    step: int,
    n_gaussians: int,
    peak_gpu_bytes: int,
    in_field: np.ndarray | None = None,
    stamp: float | None = None,
    earlier_snapshots_s: float = 0.0,
) -> float:
    """The atoms as they stand after ``step`` steps and the wall-clock time:
    ``step-NNNNNN.csv`` and a line ``step,unix_time,gaussians,peak_gpu_bytes,earlier_s,own_s``
    in ``times.csv``; returns ``own_s``.

    ``stamp`` (default now): when the step's atoms were ready; ``earlier_s`` and ``own_s``: what the
    earlier snapshots and this one cost the run, which benchmarks subtract (:func:`read_snapshot_times`).

    With ``in_field`` ((N,) bool, the density control's test of the field of view) the file holds
    the Gaussians the run would report as atoms were it stopped here (:func:`reported_as_atoms`)."""
    stamp = time.time() if stamp is None else stamp
    directory.mkdir(parents=True, exist_ok=True)
    if in_field is not None:
        atoms = atoms.subset(reported_as_atoms(atoms.positions, in_field))
    write_atoms(atoms, directory / f"step-{step:06d}.csv")
    own = time.time() - stamp
    with open(directory / "times.csv", "a") as f:
        f.write(f"{step},{stamp:.3f},{n_gaussians},{peak_gpu_bytes},{earlier_snapshots_s:.3f},{own:.3f}\n")
    return own


def read_snapshot_times(directory: Path) -> tuple[list[tuple[int, float, int, int]], float]:
    """``times.csv``'s rows as (step, seconds since the epoch less the earlier snapshots' cost,
    gaussians, peak GPU bytes), and what all the snapshots cost the run (subtract it from a
    time after the last).  Files from before the cost was recorded read it as 0."""
    rows, total = [], 0.0
    for line in (Path(directory) / "times.csv").read_text().splitlines():
        fields = line.split(",")
        earlier, own = (float(fields[4]), float(fields[5])) if len(fields) > 5 else (0.0, 0.0)
        rows.append((int(fields[0]), float(fields[1]) - earlier, int(fields[2]), int(float(fields[3]))))
        total = earlier + own
    return rows, total
