"""Check each atom's stated position precision against its actual error, on finished runs
whose data have a truth file.

For every run: the atoms it wrote (``atoms.csv``: each position with the precision the run
states, its neighbours re-fitted and any floor given) are matched to the true atoms the run's own
``evaluation.json`` counts (inside the field it reports, less those whose partner is a Gaussian it
placed beyond it; 0.75 Å, one to one, as that file and ``evaluate`` match them), and the matched
atoms' actual errors read against what was stated.  Reported per axis: median stated standard
deviation, actual RMS error, their ratio, the share within one
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
    from gaussian_atoms_method.nerfstudio_layer.launch import load_model

    return precision_of_run(load_model(config), Path(config).parent)


def precision_of_run(model, run_dir: Path) -> dict:
    """:func:`check_precision` of the run in ``run_dir`` whose ``model`` is loaded."""
    from gaussian_atoms_method.atoms.atom_set import read_atoms
    from gaussian_atoms_method.atoms.evidence import evidence_scores
    from gaussian_atoms_method.atoms.matching import match_atoms
    from gaussian_atoms_method.engine.results import counted_truth, truth_in_field

    atoms = read_atoms(Path(run_dir) / "atoms.csv")
    truth = read_atoms(model.truth_path)
    others = Path(run_dir) / "non_atoms.xyz"
    others_A = read_atoms(others).positions if others.is_file() else np.zeros((0, 3))
    beyond_A = others_A[~truth_in_field(model, others_A)] if len(others_A) else others_A
    counted = counted_truth(model, truth.positions, atoms.positions, beyond_A)  # as the run scored itself
    pred_idx, true_idx = match_atoms(atoms.positions, truth.positions, 0.75)
    keep = counted[true_idx]
    pred_idx, true_idx = pred_idx[keep], true_idx[keep]
    err = atoms.positions[pred_idx] - truth.positions[true_idx]
    s = atoms.position_std_A[pred_idx]
    total_pred = np.sqrt((s**2).sum(axis=1))
    total_err = np.sqrt((err**2).sum(axis=1))
    # no atom matched (a run that found none of the truth): no quartiles to read
    edges = np.quantile(total_pred, [0.25, 0.5, 0.75]) if len(total_pred) else np.full(3, np.inf)
    # evaluate's own reading (none where no atom is matched)
    coverage = evidence_scores(atoms, truth, truth_counted=counted).get("coverage_95_xyz", [np.nan] * 3)
    return {
        "run": str(run_dir),
        "data": str(model.truth_path.parent.name),
        "matched": len(pred_idx),
        "pred_pm": np.median(s, axis=0) * 100 if len(s) else np.full(3, np.nan),
        "actual_pm": np.sqrt((err**2).mean(axis=0)) * 100 if len(s) else np.full(3, np.nan),
        "within_1": np.mean(np.abs(err) < s, axis=0) if len(s) else np.full(3, np.nan),
        "coverage_95": np.asarray(coverage, dtype=np.float64),
        "quartiles": [
            (np.median(total_pred[in_q]) * 100, np.sqrt(np.mean(total_err[in_q] ** 2)) * 100)
            if in_q.any()
            else (np.nan, np.nan)
            for in_q in (np.digitize(total_pred, edges)[None, :] == np.arange(4)[:, None])
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
