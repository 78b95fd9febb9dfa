"""Replicas of Ta film sub-areas fitted as the film they lie in: each asked sub-area's replica
with its strip neighbours' (:func:`neighbourhood`), fitted by ``gaussian-atoms film``'s defaults
(every sub-area without and with per-view shifts and gains, the registration each keeps decided
by its overlapping neighbours, :mod:`gaussian_atoms_method.film.registration`), and the asked
ones scored against their replicas' truths.

Why a film: a replica carries a misregistration (0.5 px per view, :data:`.film_benchmark.REPLICA`)
that a lone series cannot decide to learn (its own residual always prefers more freedom), as
the real sub-areas do; the film's overlap decides it without a truth.  Each replica is drawn
from the authors' model in its own sub-area's geometry with its own noise, support and
misregistration (seeded by the sub-area's number), so neighbours share atoms and nothing else.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from gaussian_atoms_method.harness.film_benchmark import (
    FULL_VOLUME_CENTRE_VOX,
    PIXEL_SIZE_A,
    area_geometry,
    prepare_area,
    write_replica,
)
from gaussian_atoms_method.harness.film_strip import STRIPS


def neighbourhood(areas) -> list[int]:
    """The sub-areas ``areas`` and their neighbours along their published strip (the sub-areas
    before and after, which overlap them most), sorted.

    >>> neighbourhood([8, 23, 25])
    [7, 8, 9, 22, 23, 24, 25, 26]
    >>> neighbourhood([17])
    [17, 18]
    """
    strip_of = {a: strip for strip, members in STRIPS.items() for a in members}
    unknown = [a for a in areas if a not in strip_of]
    if unknown:
        raise ValueError(f"--areas: no published sub-area {unknown[0]}; they are 1-29")
    return sorted({n for a in areas for n in (a - 1, a, a + 1) if strip_of.get(n) == strip_of[a]})


def replica_subareas(data_dir: Path, out_dir: Path, areas: list[int], species: str = "Ta") -> list:
    """Each of ``areas`` written as its replica (:func:`.film_benchmark.write_replica`, seed the
    sub-area's number), placed in the film's frame as the real sub-area is (its crop's centre)."""
    from gaussian_atoms_method.film.subareas import subarea_at

    out = []
    for area in areas:
        real = prepare_area(data_dir, Path(out_dir) / "data", area, species)
        replica = write_replica(real, Path(out_dir) / "data" / "replica" / f"area{area}", seed=area)
        cen, _ = area_geometry(data_dir, area)
        out.append(subarea_at(f"area{area}", replica, (cen - np.asarray(FULL_VOLUME_CENTRE_VOX)) * PIXEL_SIZE_A))
    return out


def replica_film(benchmark, tasks_per_gpu: int = 1) -> list[dict]:
    """Fit ``benchmark``'s (a :class:`.film_benchmark.FilmBenchmark` with ``replica``) asked
    sub-areas' replicas with their neighbours as one film under ``benchmark.output / "film"``
    (resumable), the specimen said to be a film; print and write (``results.md``,
    ``results.csv``) each asked sub-area's row: its kept fit's scores (``benchmark.score``),
    ``seconds`` (that fit's), ``registered`` (whether it kept the per-view shifts and gains)."""
    from gaussian_atoms_method.atoms.atom_set import read_atoms
    from gaussian_atoms_method.film.film import reconstruct_film
    from gaussian_atoms_method.film.runner import DONE, place_of

    if benchmark.flags or benchmark.start_from_model:
        raise ValueError(
            "--train-args and --start-from-model: not with --replica's film (add --no-registration-by-overlap)"
        )
    output = Path(benchmark.output)
    subareas = replica_subareas(benchmark.data_dir, output, neighbourhood(benchmark.areas), benchmark.species or "Ta")
    film_dir = output / "film"
    reconstruct_film(
        subareas,
        film_dir,
        benchmark.device,
        benchmark.species or None,
        max_steps=benchmark.iterations,
        progress=False,
        tasks_per_gpu=tasks_per_gpu,
        extended_object="on",
    )
    chosen = json.loads((film_dir / "registration.json").read_text())["chosen"]
    by_name = {s.name: s for s in subareas}
    rows = []
    for area in benchmark.areas:
        name = f"area{area}"
        place = place_of(film_dir / "runs" / chosen[name], name)
        record = json.loads((place.run_dir / DONE).read_text())
        atoms = read_atoms(record["atoms"])
        scores = benchmark.score(area, by_name[name].data, atoms)
        rows.append(
            {"area": area, **scores, "seconds": record["fit_s"], "registered": chosen[name] == "with_registration"}
        )
        benchmark.say(
            rows[-1], " (kept the per-view shifts and gains)" if rows[-1]["registered"] else " (kept the fit without)"
        )
    benchmark.write(rows)
    return rows
