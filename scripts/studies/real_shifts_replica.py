"""What the real views' misregistration does to a fit and to its evidence: replicas of a Ta-film
sub-area given the shifts the real views hold, fitted with per-view shifts off and on.

Fits the real sub-area with ``refine_alignment`` on, reads each view's shift against that fit's
Gaussians (``best_registration`` over the detector's interior), writes two replicas of the
sub-area (the authors' model as their truth, ``benchmark-film``'s experiment, seeds 100 + and
200 + the sub-area) with those shifts instead of random ones, fits each both ways and prints each
fit's scores and evidence against the truth in ``benchmark-film``'s region; then each replica's
intervals with the floor the other replica read, fitted the same way (docs/evidence.md).

    python scripts/studies/real_shifts_replica.py --area 23 --device cuda
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--area", type=int, required=True, help="a sub-area of the film (8, 21, 23, 25, ...)")
    parser.add_argument("--film", type=Path, default=Path("../shared/data/ta_film"), help="the film's folder")
    parser.add_argument("--device", default="auto")
    args = parser.parse_args()
    try:
        report(args)
    except (OSError, ValueError) as err:  # a missing film folder or file
        raise SystemExit(f"real_shifts_replica.py: {err}") from None


def report(args) -> None:
    import json

    import gaussian_atoms_method as ga
    from dataparsers.registration_file import read_registration
    from dataparsers.tilt_series_format import load_tilt_series
    from gaussian_atoms_method.atoms.atom_set import read_atoms
    from gaussian_atoms_method.atoms.calibration import with_floor
    from gaussian_atoms_method.atoms.view_prediction import (
        best_registration,
        interior,
        predicted_views,
        run_gaussians,
    )
    from gaussian_atoms_method.harness import film_benchmark as fb
    from gaussian_atoms_method.harness import replica

    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        area_dir = fb.prepare_area(args.film, work, args.area, "Ta")
        meta = json.loads((area_dir / "tilt_series.json").read_text())
        shape = np.load(area_dir / meta["projections"], mmap_mode="r").shape[1:]
        model = fb.model_in_area_A(args.film, args.area)
        box, inside = fb.scored_region(model, shape, tuple(meta["centre_px"]))

        def said(tag: str, atoms) -> dict:
            s = fb.score_in_region(atoms.positions, model, box, inside)
            e = fb.evidence_in_region(atoms, model, box, inside, s["shift_A"])
            print(
                f"{tag}: found {s['found']:.3f}, extra {s['extra_per_model_atom']:.3f}, {s['rmsd_pm']:.1f} pm"
                + fb.evidence_words(e)
            )
            return e

        def fit(directory: Path, tag: str, **options):
            atoms = ga.reconstruct(
                ga.read_tilt_series(directory), species="Ta", device=args.device, progress=False, **options
            )
            return atoms, said(tag, atoms)

        registered = fit(
            area_dir, "real views, registration on, against the model", refine_alignment=True, output_dir=work / "run"
        )[0]
        run_dir = registered.info["run_dir"]
        series = load_tilt_series(area_dir)
        # every Gaussian of the fit: the film beyond the field is in the views too
        measured, predicted = (
            np.asarray(series.projections, np.float64),
            predicted_views(run_gaussians(run_dir), series),
        )
        shifts = np.array(
            [
                best_registration(interior(m[None], fb.INTERIOR_PX)[0], interior(p[None], fb.INTERIOR_PX)[0])[0]
                for m, p in zip(measured, predicted)
            ]
        )
        rms = np.sqrt(np.mean(shifts**2, axis=0))
        most = np.abs(shifts).max()
        print(f"the real views' shifts: {rms[0]:.2f} / {rms[1]:.2f} px RMS (rows / columns), up to {most:.2f}")
        learned = read_registration(run_dir / "registration.csv")[0]
        off = np.sqrt(np.mean((learned - shifts) ** 2, axis=0))
        print(f"the fit's registration.csv differs from them by {off[0]:.2f} / {off[1]:.2f} px RMS")
        settings = {**fb.REPLICA, "shifts_px": shifts}
        truth, fits = read_atoms(series.truth_path), {}
        seeds = (100 + args.area, 200 + args.area)
        for seed in seeds:
            out = replica.write_replica(series, truth, work / f"replica{seed}", seed=seed, **settings)[0]
            for name, options in (("off", {}), ("on", {"refine_alignment": True})):
                fits[seed, name] = fit(out, f"replica (seed {seed}) with those shifts, registration {name}", **options)
        for name in ("off", "on"):  # each replica's intervals with the other's floor
            for seed, other in (seeds, seeds[::-1]):
                atoms, floor = fits[seed, name][0], fits[other, name][1].get("precision_floor_A", np.zeros(3))
                floored = atoms.shifted(np.zeros(3))
                floored.position_std_A, floored.depth_halfwidth_A, floored.depth_open = with_floor(
                    atoms.position_std_A, atoms.depth_halfwidth_A, atoms.depth_open, floor, None
                )  # the depth flags as the fit raised them
                said(f"replica (seed {seed}), registration {name}, the floor of seed {other}'s", floored)


if __name__ == "__main__":
    main()
