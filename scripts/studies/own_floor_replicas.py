"""Does the floor a run reads on its own replica hold on data with a truth?  Each Ta sub-area's
replica (benchmark-film --replica's physics: ADF atoms, the probe with a source and a halo, a 3 nm
carbon support, 0.5 px misregistration, 6.8% gains) is fitted with the defaults twice: without
the run's own floor and with it (``own_floor``, engine/own_floor.py); the 95% intervals are
scored against the replica's truth over every atom the fit found (after the global shift), per
axis and along the beam (the depth interval).

    python scripts/studies/own_floor_replicas.py --areas 8 21 23 25 --output outputs/own_floor
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=Path("../shared/data/ta_film"))
    parser.add_argument("--areas", type=int, nargs="+", default=[8, 21, 23, 25])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--output", type=Path, default=Path("outputs/own_floor"))
    args = parser.parse_args()

    import numpy as np

    import gaussian_atoms_method as ga
    from dataparsers.tilt_series_format import load_tilt_series
    from gaussian_atoms_method.atoms.atom_set import read_atoms
    from gaussian_atoms_method.atoms.calibration import Z95
    from gaussian_atoms_method.atoms.matching import shifted_errors
    from gaussian_atoms_method.harness import film_benchmark as fb

    print(
        "| sub-area | own floor | found | false per atom | RMSD (pm) | hold x/y/z | depth hold | floor (pm) | run (s) |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    replicas = fb.FilmBenchmark(args.data, args.output, replica=True)  # benchmark-film --replica's data
    for area in args.areas:
        series = load_tilt_series(replicas.prepare(area))
        truth = read_atoms(series.truth_path).positions
        for own in (False, True):
            started = time.perf_counter()
            atoms = ga.reconstruct(
                series, species="Ta", device=args.device, progress=False, extended_object="on", own_floor=own
            )
            took = time.perf_counter() - started
            pi, ti, error = shifted_errors(atoms.positions, truth, fb.MATCH_RADIUS_A)
            stated = atoms.position_std_A[pi]
            held = "/".join(f"{c:.2f}" for c in (np.abs(error) <= Z95 * stated).mean(axis=0))
            depth = (np.abs(error[:, 2]) <= atoms.depth_halfwidth_A[pi]).mean()
            floor = atoms.info.get("precision_floor_A")
            said = "/".join(f"{f * 100:.1f}" for f in floor) if floor is not None else ""
            rmsd = np.sqrt((error**2).sum(axis=1).mean()) * 100
            print(
                f"| {area} | {'on' if own else 'off'} | {len(pi)} | {(len(atoms) - len(pi)) / len(truth):.3f} | "
                f"{rmsd:.1f} | {held} | {depth:.2f} | {said} | {took:.0f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
