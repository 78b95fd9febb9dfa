"""Check each atom's stated position precision against its actual error, on finished runs
whose data have a truth file.

For every run: the atoms it wrote (``atoms.csv``: each position with the precision the run
states, its neighbours re-fitted and any floor given) are matched to the true atoms inside the
field the run reports (0.75 Å, one to one, as the run's own ``evaluation.json`` and ``evaluate``
match them), and the matched atoms' actual errors read against what was stated.  Reported per
axis: median stated standard deviation, actual RMS error, their ratio, the share within one
stated standard deviation (0.683 if the statement were exact) and within the stated 95% interval
(``coverage_95_xyz``, 0.95 if exact: the number ``evaluate`` gives); and, in quartiles of the
stated precision, the actual RMS error (does the statement rank atoms correctly?).

    gaussian-atoms check-precision RUN/config.yml [RUN2/config.yml ...] --output docs/uncertainty_check.md
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def check_precision(config: Path) -> dict:
    """One finished run (``config.yml``) whose data have a truth file: its written atoms' stated
    precision against their actual errors, per axis and by quartile (module text)."""
    from gaussian_atoms_method.atoms.atom_set import read_atoms
    from gaussian_atoms_method.atoms.evidence import evidence_scores
    from gaussian_atoms_method.atoms.matching import match_atoms
    from gaussian_atoms_method.engine.results import truth_in_field
    from gaussian_atoms_method.nerfstudio_layer.launch import load_model

    model = load_model(config)
    atoms = read_atoms(Path(config).parent / "atoms.csv")
    truth = read_atoms(model.truth_path)
    counted = truth_in_field(model, truth.positions)
    pred_idx, true_idx = match_atoms(atoms.positions, truth.positions, 0.75)
    keep = counted[true_idx]
    pred_idx, true_idx = pred_idx[keep], true_idx[keep]
    err = atoms.positions[pred_idx] - truth.positions[true_idx]
    s = atoms.position_std_A[pred_idx]
    total_pred = np.sqrt((s**2).sum(axis=1))
    total_err = np.sqrt((err**2).sum(axis=1))
    quartile = np.digitize(total_pred, np.quantile(total_pred, [0.25, 0.5, 0.75]))
    coverage = evidence_scores(atoms, truth, truth_counted=counted)["coverage_95_xyz"]  # evaluate's own reading
    return {
        "run": str(config.parent),
        "data": str(model.truth_path.parent.name),
        "matched": len(pred_idx),
        "pred_pm": np.median(s, axis=0) * 100,
        "actual_pm": np.sqrt((err**2).mean(axis=0)) * 100,
        "within_1": np.mean(np.abs(err) < s, axis=0),
        "coverage_95": np.asarray(coverage, dtype=np.float64),
        "quartiles": [
            (np.median(total_pred[quartile == q]) * 100, np.sqrt(np.mean(total_err[quartile == q] ** 2)) * 100)
            for q in range(4)
        ],
    }


def precision_table(rows: list[dict]) -> str:
    """The rows of :func:`check_precision` as markdown tables."""
    out = (
        "| data | matched | axis | stated std (pm, median) | actual RMS (pm) | actual / stated "
        "| within 1 std | within the 95% interval |\n"
    )
    out += "| --- | --- | --- | --- | --- | --- | --- | --- |\n"
    for r in rows:
        for k, axis in enumerate("xyz"):
            lead = f"| {r['data']} | {r['matched']} " if k == 0 else "| | "
            out += (
                lead + f"| {axis} | {r['pred_pm'][k]:.1f} | {r['actual_pm'][k]:.1f} | "
                f"{r['actual_pm'][k] / r['pred_pm'][k]:.2f} | {r['within_1'][k]:.2f} | {r['coverage_95'][k]:.2f} |\n"
            )
    out += "\nBy quartile of the stated 3D precision (median stated -> actual 3D RMS error, pm):\n\n"
    out += "| data | Q1 | Q2 | Q3 | Q4 |\n| --- | --- | --- | --- | --- |\n"
    for r in rows:
        out += f"| {r['data']} | " + " | ".join(f"{p:.1f} -> {a:.1f}" for p, a in r["quartiles"]) + " |\n"
    return out
