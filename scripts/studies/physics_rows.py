"""A row of the accuracy harness on data with a truth, with the evidence scored: fit a tilt series
through the Python API (the defaults) and print found, false atoms per true atom and RMSD (0.75 Å,
after the global shift), how often the stated 95% intervals hold (x, y, z and depth) and how much
of the disagreement (misses and false atoms) the atoms called open hold; with several elements
given (``--species Ni,Pd,Pt``), the share of found atoms given their true element, and how many
of those misnamed the run left open in element.

    python scripts/studies/physics_rows.py --data SERIES [--device cuda] [--species Pd] [--option name=value ...]

``SERIES`` is a tilt-series directory whose manifest names its truth (``gaussian-atoms simulate``
writes one; ``--potential adf`` draws it through physics the fit does not share).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path


def _value(text: str):
    """An option's value as Python reads a literal (1, 0.5, True, "x"), else the text itself."""
    import ast

    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return {"true": True, "false": False}.get(text.lower(), text)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--device", default="auto")
    parser.add_argument("--species", default=None)
    parser.add_argument("--option", action="append", default=[], help="a model option as name=value")
    args = parser.parse_args()

    import numpy as np

    import gaussian_atoms_method as ga
    from dataparsers.tilt_series_format import load_tilt_series
    from gaussian_atoms_method.atoms.atom_set import AtomSet, read_atoms
    from gaussian_atoms_method.atoms.evidence import evidence_scores
    from gaussian_atoms_method.atoms.matching import global_shift, match_atoms

    options = {k: _value(v) for k, v in (o.split("=", 1) for o in args.option)}
    series = load_tilt_series(args.data)
    start = time.perf_counter()
    atoms = ga.reconstruct(series, device=args.device, species=args.species, progress=False, **options)
    seconds = time.perf_counter() - start
    truth = read_atoms(series.truth_path)
    shift = global_shift(atoms.positions, truth.positions)
    pi, ti = match_atoms(atoms.positions + shift, truth.positions, 0.75)
    error = atoms.positions[pi] + shift - truth.positions[ti]
    row = {
        "data": str(args.data),
        "atoms": len(truth),
        "found": len(pi) / len(truth),
        "false_per_atom": (len(atoms) - len(pi)) / len(truth),
        "rmsd_pm": float(np.sqrt((error**2).sum(axis=1).mean()) * 100),
        "seconds": round(seconds, 1),
        **evidence_scores(atoms.shifted(shift), AtomSet(truth.positions), 0.75),
    }
    if atoms.species is not None and truth.species is not None and args.species and "," in args.species:
        right = atoms.species[pi] == truth.species[ti]
        confidence = atoms.element_confidence[pi]
        row["found_by_element"] = {
            str(e): float(np.isin(np.flatnonzero(truth.species == e), ti).mean()) for e in np.unique(truth.species)
        }
        row["element_right"] = float(right.mean())
        row["element_right_by_element"] = {
            str(e): float(right[truth.species[ti] == e].mean()) for e in np.unique(truth.species[ti])
        }
        row["element_confidence_mean"] = float(np.nanmean(confidence)) if np.isfinite(confidence).any() else None
        row["misnamed_open_in_element"] = float((confidence[~right] < 0.95).mean()) if (~right).any() else None
    print(json.dumps(row))


if __name__ == "__main__":
    main()
