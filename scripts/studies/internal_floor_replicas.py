"""Does the floor an internal replica reads hold on data with a truth?  Each Ta sub-area's replica
(benchmark-film --replica's physics: ADF atoms, the probe with a source and a halo, a 3 nm carbon
support, 0.5 px misregistration, 6.8% gains) is fitted with the defaults (the film said); then
``internal_floor`` (the support named) reads the floor on a replica of the fit's own atoms; the
95% intervals are scored against the replica's truth, as stated and with the floor, over every
atom the fit found.

    python scripts/studies/internal_floor_replicas.py --areas 8 21 23 25 --output outputs/internal_floor
"""

from __future__ import annotations

import argparse
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=Path("../shared/data/ta_film"))
    parser.add_argument("--areas", type=int, nargs="+", default=[8, 21, 23, 25])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--support-A", type=float, default=30.0)
    parser.add_argument("--output", type=Path, default=Path("outputs/internal_floor"))
    args = parser.parse_args()

    import numpy as np

    import gaussian_atoms_method as ga
    from dataparsers.tilt_series_format import load_tilt_series
    from gaussian_atoms_method.atoms.atom_set import read_atoms
    from gaussian_atoms_method.atoms.calibration import Z95, precision_floor_A
    from gaussian_atoms_method.atoms.matching import shifted_errors
    from gaussian_atoms_method.harness import film_benchmark as fb
    from gaussian_atoms_method.harness.internal_floor import internal_floor

    print("| sub-area | found | RMSD (pm) | stated: hold x/y/z | internal floor (pm) | with it | truth's floor (pm) |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    replicas = fb.FilmBenchmark(args.data, args.output, replica=True)  # benchmark-film --replica's data
    for area in args.areas:
        series = load_tilt_series(replicas.prepare(area))
        atoms = ga.reconstruct(series, species="Ta", device=args.device, progress=False, extended_object="on")
        truth = read_atoms(series.truth_path).positions
        pi, ti, error = shifted_errors(atoms.positions, truth, fb.MATCH_RADIUS_A)
        stated = atoms.position_std_A[pi]
        floor = internal_floor(
            series, atoms, species="Ta", device=args.device, support_A=args.support_A, extended_object="on"
        )
        widened = np.sqrt(stated**2 + floor.floor_A**2)

        def held(std):
            return "/".join(f"{c:.2f}" for c in (np.abs(error) <= Z95 * std).mean(axis=0))

        pm = lambda v: "/".join(f"{x * 100:.1f}" for x in v)  # noqa: E731
        rmsd = np.sqrt((error**2).sum(axis=1).mean()) * 100
        print(
            f"| {area} | {len(pi)} | {rmsd:.1f} | {held(stated)} | {pm(floor.floor_A)} | {held(widened)} | "
            f"{pm(precision_floor_A(error, stated))} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
