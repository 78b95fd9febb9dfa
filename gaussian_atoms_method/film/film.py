"""A whole film from its sub-areas: fit each (:mod:`.runner`), join them in the film's frame
(:mod:`.stitch`) and write the film's atoms, its non-atoms, the overlap's evidence and a figure.

Outputs in ``output_dir``: ``film.json`` (the sub-areas), ``runs/<set>/<sub-area>/`` (each fit;
``<set>`` ``without_registration`` and ``with_registration`` where the overlap decides the
registration, none otherwise),
``atoms.xyz`` (the confirmed atoms, Å in the film's frame), ``non_atoms.xyz`` (the rest),
``atoms.csv`` (every joined atom with ``found_in``, ``covered_by``, whether confirmed and the
spread of its reports, ``spread_{x,y,z}_A``),
``film.png`` (the film seen from above, coloured by ``found_in / covered_by``),
``overlaps.csv`` (each pair of overlapping sub-areas: the share of the atoms one fit reports in
their common interior that the other reports too, each way, and how far apart the two place the
atoms both report against their stated precisions), ``summary.json`` and, where the overlap
decides the registration, ``registration.json`` (:mod:`.registration`).
"""

from __future__ import annotations

import json
import math
from dataclasses import fields
from pathlib import Path

import numpy as np

from gaussian_atoms_method.atoms.atom_set import AtomSet, read_atoms, write_atoms
from gaussian_atoms_method.atoms.hard_core import hard_core_from_species, parse_species
from gaussian_atoms_method.engine.console import CONSOLE
from gaussian_atoms_method.film.classes import film_split, read_gaussians
from gaussian_atoms_method.film.registration import SETS, registration_words
from gaussian_atoms_method.film.registration import registration_by_overlap as registration_by_overlap_of
from gaussian_atoms_method.film.runner import check_address, run_subareas
from gaussian_atoms_method.film.stitch import (
    FilmAtoms,
    PairAgreement,
    Reports,
    join_reports,
    pair_agreement,
    write_overlaps,
)
from gaussian_atoms_method.film.subareas import SubArea, write_plan


class FilmError(RuntimeError):
    """Sub-areas that failed (named in the message); the others' fits are kept for a resume."""


def reconstruct_film(
    subareas: list[SubArea],
    output_dir: Path,
    device: str = "auto",
    species: str | None = None,
    max_steps: int = 3000,
    address: str | None = None,
    progress: bool = True,
    tasks_per_gpu: int = 1,
    registration_by_overlap: bool = True,
    **model_options,
) -> FilmAtoms:
    """Fit ``subareas``, join them and write the film (module text).

    ``device``: ``auto`` (the GPUs where the cluster has them), ``cpu`` or ``cuda``.  ``species``
    sets the hard core of every sub-area's fit and of the join (else the median of the fits' own
    readings).  ``tasks_per_gpu`` sub-areas share each GPU (:func:`~.runner.run_subareas`);
    ``model_options`` are the fit's options by their Python names.  The arguments are checked
    before anything is written (:func:`check_settings`).  Raises :class:`FilmError` naming
    the sub-areas that failed after a retry; the others' fits stay, and a second call runs only
    those.

    ``registration_by_overlap`` (default): fit every sub-area twice, without and with per-view
    shifts and gains (``refine_alignment``, ``refine_gain``; ``runs/without_registration``,
    ``runs/with_registration``), and join for each sub-area the fit its overlapping neighbours
    prefer (:mod:`~.registration`; ``registration.json``): twice the fits' time.  False: one fit
    each, under ``runs``, with the registration ``model_options`` give."""
    species, device = check_settings(device, species, max_steps, address, tasks_per_gpu, model_options)
    given = sorted({"refine_alignment", "refine_gain"} & set(model_options))
    if registration_by_overlap and given:
        raise ValueError(f"{given[0]}: registration_by_overlap decides it; give one or the other")
    if not subareas:
        raise ValueError("subareas: none given (read them with published_subareas or tile_series)")
    output_dir = Path(output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    write_plan(subareas, output_dir / "film.json")
    fitted = (subareas, device, max_steps, address, progress, tasks_per_gpu, species)
    if registration_by_overlap:
        tried = {
            name: _fit_and_judge(output_dir / "runs" / name, {**model_options, **options}, *fitted)
            for name, options in SETS.items()
        }
        hard_core_A = tried["without_registration"][2]
        choice = registration_by_overlap_of({name: t[1] for name, t in tried.items()}, hard_core_A)
        (output_dir / "registration.json").write_text(json.dumps(choice, indent=1) + "\n")
        CONSOLE.print(f"gaussian-atoms film: {registration_words(choice)}")
        kept = [choice["chosen"][s.name] for s in subareas]
        records = {s.name: tried[k][0][s.name] for s, k in zip(subareas, kept)}
        reports = [tried[k][1][i] for i, k in enumerate(kept)]
        pairs = pair_agreement(reports, hard_core_A)
    else:
        records, reports, hard_core_A, pairs = _fit_and_judge(output_dir / "runs", model_options, *fitted)
    film = join_reports(reports, hard_core_A)
    write_film(
        film, output_dir, hard_core_A, [s.name for s in subareas], task_summary(records.values()), species, pairs
    )
    return film


def _fit_and_judge(runs_dir, options, subareas, device, max_steps, address, progress, tasks_per_gpu, species):
    """Every sub-area fitted under ``runs_dir`` with ``options``: their records, their reports in
    the film's frame, the hard core they are joined by and their overlapping pairs' agreement."""
    records, failures = run_subareas(
        subareas, runs_dir, options, device, max_steps, address, progress, tasks_per_gpu, species
    )
    if failures:
        named = "; ".join(f"{name}: {why}" for name, why in sorted(failures.items()))
        raise FilmError(f"{len(failures)} of {len(subareas)} sub-areas failed ({named}); run again to retry them")
    cores = [r["hard_core_A"] for r in records.values() if r.get("hard_core_A")]
    hard_core_A = hard_core_from_species(species) if species else float(np.median(cores)) if cores else math.nan
    reports = film_reports(subareas, records, hard_core_A)
    return records, reports, hard_core_A, pair_agreement(reports, hard_core_A)


def film_reports(subareas: list[SubArea], records: dict, hard_core_A: float) -> list[Reports]:
    """Each sub-area's atoms in the film's frame, split from its non-atoms by one class decision
    over the film (:mod:`.classes`, said in a line); where a fit wrote no non-atoms, the fits'
    own splits (their ``atoms``)."""
    sets = [read_gaussians(records[s.name]["atoms"], s) for s in subareas]
    if all(g is not None for g in sets):
        split = film_split(sets, hard_core_A)
        CONSOLE.print(f"gaussian-atoms film: {split.words(sets)}")
        chosen = [
            (g.positions[k], g.position_std_A[k], None if g.trusted is None else g.trusted[k])
            for g, k in zip(sets, split.kept)
        ]
    else:
        atoms = [read_atoms(records[s.name]["atoms"]) for s in subareas]
        chosen = [
            (a.positions, a.position_std_A, None if a.trusted is None else np.asarray(a.trusted) > 0) for a in atoms
        ]
    return [
        Reports(s.name, positions + np.asarray(s.offset_A), s.interior_A, std, trusted)
        for s, (positions, std, trusted) in zip(subareas, chosen)
    ]


ARGUMENT_NAMES = {"device": "device", "max_steps": "max_steps", "tasks_per_gpu": "tasks_per_gpu"}
"""How :func:`check_settings` names the arguments it checks (the command line passes its options')."""


def check_settings(
    device, species, max_steps, address, tasks_per_gpu, model_options, names: dict = ARGUMENT_NAMES
) -> tuple[str, str]:
    """:func:`reconstruct_film`'s settings checked before anything is written (a ValueError
    naming the first that is wrong, by ``names``); returns the species as one string ("" for
    none) and the device (``auto`` resolved on a local cluster)."""
    from gaussian_atoms_method.engine.options import FitOptions
    from gaussian_atoms_method.physics.devices import resolve, usable

    unknown = sorted(set(model_options) - {f.name for f in fields(FitOptions)})
    if unknown:
        raise ValueError(f"{unknown[0]}: not a model option (the options of `ns-train gaussian-atoms --help`)")
    FitOptions(**model_options).check()
    _check_count(tasks_per_gpu, names["tasks_per_gpu"], "tasks")
    species = ",".join(parse_species(species)) if species else ""
    _check_count(max_steps, names["max_steps"], "training steps")
    if address is not None:  # another cluster: its devices, asked of it once joined (runner.cluster_device)
        check_address(address)
        return species, device
    if device == "cuda" and not usable("cuda"):  # a local cluster: this machine's devices
        raise ValueError(f"{names['device']} cuda: torch sees no GPU on this machine; use cpu or auto")
    return species, resolve(device)


def _check_count(value, name: str, what: str) -> None:
    """A ValueError naming ``name`` unless ``value`` is a whole number (not a bool) of at least 1."""
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name} {value!r}: expected a whole number of {what}, at least 1")


def task_summary(records) -> dict:
    """The sub-area tasks' costs (:func:`~.runner.task_costs`) over ``records``: the median and
    largest fit time, the largest GPU peak and worker memory (None where no record has it: fits
    made before the costs were recorded, or on the CPU for the GPU's), and how many of the fits
    that recorded it (``convergence_known``) converged before the step limit."""

    def values(key):
        return [r[key] for r in records if r.get(key) is not None]

    fit_s, gpu, rss = values("fit_s"), values("peak_gpu_GB"), values("worker_rss_GB")
    converged = values("converged")
    return {
        "converged": sum(converged) if converged else None,
        "convergence_known": len(converged),
        "median_fit_s": float(np.median(fit_s)) if fit_s else None,
        "max_fit_s": max(fit_s) if fit_s else None,
        "max_peak_gpu_GB": max(gpu) if gpu else None,
        "max_worker_rss_GB": max(rss) if rss else None,
    }


def write_film(
    film: FilmAtoms,
    output_dir: Path,
    hard_core_A: float,
    names: list[str],
    tasks: dict | None = None,
    species: str = "",
    pairs: list[PairAgreement] | None = None,
) -> None:
    """The film's files (module text) and its summary line; ``tasks``: the sub-areas' costs
    (:func:`task_summary`), in the summary; ``species`` ("Ta"): a film of one element names its
    atoms by it (of several, the joined atoms keep no mass to tell them apart by: ``X``);
    ``pairs``: the overlapping sub-areas' agreement (:func:`~.stitch.pair_agreement`)."""
    output_dir = Path(output_dir)
    tasks = tasks or {}
    elements = parse_species(species)
    atoms = AtomSet(
        positions=film.positions[film.reported],
        species=np.full(int(film.reported.sum()), elements[0]) if len(elements) == 1 else None,
    )
    rest = AtomSet(positions=film.positions[~film.reported])
    write_atoms(atoms, output_dir / "atoms.xyz")
    write_atoms(rest, output_dir / "non_atoms.xyz")
    spread = film.spread_A if film.spread_A is not None else np.full((len(film.positions), 3), np.nan)
    unsaid = np.full(len(film.positions), np.nan)  # the fits did not say which atoms they trust
    trusted_in, trusted = (unsaid, unsaid) if film.trusted is None else (film.trusted_in, film.trusted)
    table = np.column_stack(
        [
            film.positions,
            film.found_in,
            film.covered_by,
            film.confirmed.astype(int),
            film.reported.astype(int),
            spread,
            trusted_in,
            trusted,
        ]
    )
    np.savetxt(
        output_dir / "atoms.csv",
        table,
        delimiter=",",
        header="x_A,y_A,z_A,found_in,covered_by,confirmed,reported,spread_x_A,spread_y_A,spread_z_A,trusted_in,trusted",
        comments="",
        fmt=["%.4f", "%.4f", "%.4f", "%d", "%d", "%d", "%d", "%.4f", "%.4f", "%.4f", "%.0f", "%.0f"],
    )
    share = film.found_in / np.maximum(film.covered_by, 1)
    median = f"{np.median(film.found_in[film.reported])}/{np.median(film.covered_by[film.reported])}"
    summary = {
        "sub_areas": names,
        "atoms": int(film.reported.sum()),
        "confirmed_by_overlap": int(film.confirmed.sum()),
        "overlap_separates": bool(film.separated),
        "non_atoms": int((~film.reported).sum()),
        "trusted": None if film.trusted is None else int(film.trusted.sum()),
        "hard_core_A": hard_core_A,
        "recurrence_real": film.rate_real,
        "recurrence_artefact": film.rate_artefact,
        "median_found_in_of_covered_by": median if film.reported.any() else None,
        "tasks": tasks,
    }
    pairs = pairs or []
    write_overlaps(pairs, output_dir / "overlaps.csv")
    judged = [p for p in pairs if np.isfinite(p.both_ways)]
    least = min(judged, key=lambda p: p.both_ways) if judged else None
    summary["overlap_agreement"] = (
        {
            "pairs": len(judged),
            "median_both_ways": float(np.median([p.both_ways for p in judged])),
            "least": [least.a, least.b, least.both_ways],
            **positions_agree(judged),
        }
        if least
        else None
    )
    (output_dir / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    _draw(film.positions, share, output_dir / "film.png")
    if film.separated:
        said = (
            f"{summary['atoms']} atoms confirmed by the overlapping fits of {len(names)} sub-areas (median found in "
            f"{median}; a real atom recurs in {film.rate_real:.0%} of the fits that cover it, an artefact in "
            f"{film.rate_artefact:.0%}); {summary['non_atoms']} non-atoms"
        )
    else:
        said = (
            f"{summary['atoms']} atoms from the fits of {len(names)} sub-areas, none confirmed by their overlap: the "
            f"share of covering fits that find an atom does not separate real atoms from artefacts "
            f"({film.rate_real:.0%} and {film.rate_artefact:.0%}; median found in {median}: too few fits cover each "
            f"atom, or no artefacts)"
        )
    if tasks.get("convergence_known") and tasks["converged"] < tasks["convergence_known"]:
        said += (
            f"; {tasks['convergence_known'] - tasks['converged']} of {tasks['convergence_known']} sub-areas stopped at "
            f"the step limit before their atoms converged (done.json's converged; give more steps)"
        )
    if film.trusted is not None:
        said += (
            f"; {summary['trusted']} trusted (atoms.csv's trusted: a majority of the fits that found one trust it: "
            f"proven, closed in depth, one atom wide)"
        )
    if least is not None:
        said += (
            f"; overlapping fits report each other's atoms in their common interior: median "
            f"{summary['overlap_agreement']['median_both_ways']:.3f} both ways over {len(judged)} pairs, least "
            f"{least.both_ways:.3f} ({least.a} and {least.b}; overlaps.csv)"
        )
        agree = summary["overlap_agreement"]
        if "median_scatter_pm" in agree:
            said += (
                "; the atoms both report lie "
                + " / ".join(f"{v:.1f}" for v in agree["median_scatter_pm"])
                + " pm RMS apart (x / y / z, the pairs' median), within their stated 95% intervals for "
                + " / ".join(f"{v:.2f}" for v in agree["median_intervals_hold"])
            )
    CONSOLE.print(f"gaussian-atoms film: {said}; {output_dir / 'atoms.xyz'}")


def positions_agree(pairs: list[PairAgreement]) -> dict:
    """The overlapping pairs' positions judged (:class:`~.stitch.PairAgreement`): the median over
    ``pairs`` of the atoms' RMS difference along x, y, z (pm) and of the share within their stated
    intervals; empty where no pair states its precision."""
    stated = [p for p in pairs if np.all(np.isfinite(p.intervals_hold))]
    if not stated:
        return {}
    return {
        "median_scatter_pm": np.median([p.scatter_pm for p in stated], axis=0).tolist(),
        "median_intervals_hold": np.median([p.intervals_hold for p in stated], axis=0).tolist(),
    }


def _draw(positions: np.ndarray, share: np.ndarray, path: Path) -> None:
    from gaussian_atoms_method.atoms.pictures import pyplot

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8, 4))
    points = ax.scatter(positions[:, 0], positions[:, 1], c=share, s=4, cmap="viridis", vmin=0, vmax=1)
    fig.colorbar(points, ax=ax, label="found in / covered by")
    ax.set_xlabel("x (Å, across the tilt axis)")
    ax.set_ylabel("y (Å, along it)")
    ax.set_aspect("equal")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
