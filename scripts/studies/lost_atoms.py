"""Where the true atoms a fit misses went: fit a simulated tilt series through the Python API
and sort each missed true atom by what lies near it.

    python scripts/studies/lost_atoms.py --data SERIES --output DIR [--device cuda] [--option name=value ...]

``SERIES`` is a tilt-series directory whose manifest names its truth (``gaussian-atoms simulate``
writes one).  Each missed true atom (no predicted atom within 0.75 Å, one to one, after the
global shift) is put in the first class that holds:

- ``shared``: a predicted atom within 0.75 Å, matched to another true atom (one Gaussian holds
  two atoms, or two true atoms compete for one);
- ``non_atom``: a Gaussian the run reported as a non-atom within 0.75 Å;
- ``displaced``: a predicted atom 0.75-1.5 Å away (its direction's |cos| to the beam at zero
  tilt is reported: 1 is along the beam);
- ``absent``: nothing within 1.5 Å.

For each class: how many, the share of the missed atoms whose nearest true neighbour lies within
the hard core's reach of another missed one, the mean depth of the column they sit in (true
atoms within 1.2 Å of the same beam line), and the mean nearest-true-neighbour distance.
Writes ``DIR/lost_atoms.json`` and prints it.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree


def _value(text: str):
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return {"true": True, "false": False}.get(text.lower(), text)


def classify(pred: np.ndarray, non_atoms: np.ndarray, truth: np.ndarray, radius_A: float = 0.75) -> dict:
    """The missed true atoms of (N, 3) ``truth`` sorted by what lies near them (module docstring);
    ``pred`` (M, 3) after the global shift, ``non_atoms`` (K, 3) likewise."""
    from gaussian_atoms_method.atoms.matching import match_atoms

    pi, ti = match_atoms(pred, truth, radius_A)
    found = np.zeros(len(truth), bool)
    found[ti] = True
    missed = np.flatnonzero(~found)
    tree_pred = cKDTree(pred)
    d_pred, j_pred = tree_pred.query(truth[missed], k=1)
    d_non = cKDTree(non_atoms).query(truth[missed], k=1)[0] if len(non_atoms) else np.full(len(missed), np.inf)
    nn_true = cKDTree(truth).query(truth[missed], k=2)[0][:, 1]
    column = cKDTree(truth[:, :2]).query_ball_point(truth[missed, :2], 1.2, return_length=True)
    label = np.where(
        d_pred < radius_A,
        "shared",
        np.where(d_non < radius_A, "non_atom", np.where(d_pred < 2 * radius_A, "displaced", "absent")),
    )
    out = {"true": len(truth), "found": float(found.mean()), "missed": len(missed), "classes": {}}
    for name in ("shared", "non_atom", "displaced", "absent"):
        sel = label == name
        entry = {"count": int(sel.sum())}
        if sel.any():
            entry |= {
                "column_atoms_mean": float(column[sel].mean()),
                "nearest_true_A_mean": float(nn_true[sel].mean()),
            }
            if name == "displaced":
                v = pred[j_pred[sel]] - truth[missed[sel]]
                entry["cos_beam_mean"] = float(np.mean(np.abs(v[:, 2]) / np.linalg.norm(v, axis=1)))
        out["classes"][name] = entry
    columns = cKDTree(truth[:, :2]).query_ball_point(truth[:, :2], 1.2, return_length=True)
    out["all_column_atoms_mean"] = float(columns.mean())
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--output", type=Path, required=True)
    parser.add_argument("--device", default="auto")
    parser.add_argument("--species", default=None)
    parser.add_argument("--option", action="append", default=[], help="a model option, name=value")
    args = parser.parse_args()

    import gaussian_atoms_method as ga
    from gaussian_atoms_method.atoms.atom_set import read_atoms
    from gaussian_atoms_method.atoms.matching import global_shift

    series = ga.read_tilt_series(args.data)
    manifest = json.loads((args.data / "tilt_series.json").read_text())
    truth = read_atoms(args.data / manifest["truth"]).positions
    options = dict(o.split("=", 1) for o in args.option)
    start = time.perf_counter()
    atoms = ga.reconstruct(
        series,
        device=args.device,
        species=args.species,
        output_dir=args.output,
        progress=False,
        **{k: _value(v) for k, v in options.items()},
    )
    seconds = time.perf_counter() - start
    runs = sorted((args.output / "reconstruct" / "gaussian-atoms").iterdir())
    non_path = runs[-1] / "non_atoms.xyz"
    non = read_atoms(non_path).positions if non_path.is_file() else np.zeros((0, 3))
    shift = global_shift(atoms.positions, truth)
    result = classify(atoms.positions + shift, non + shift, truth) | {
        "predicted": len(atoms.positions),
        "seconds": seconds,
        "options": options,
        "data": str(args.data),
    }
    (args.output / "lost_atoms.json").write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
