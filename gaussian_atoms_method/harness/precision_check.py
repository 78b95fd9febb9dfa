"""Check each atom's predicted position precision against its actual error, on finished runs
whose data have a truth file.

For every run: the run is loaded as ns-viewer loads it, each atom's precision comes from
:meth:`GaussianAtomsModel.position_std_A` (the curvature of the data term, with the noise
estimated from the residuals), and the atoms matched to a true atom (0.75 Å) give the actual
errors.  Reported per axis: median predicted standard deviation, actual RMS error, their ratio,
and the fraction of errors within one and two predicted standard deviations (0.683 and 0.954
if the prediction were exact); and, in quartiles of the predicted precision, the actual RMS
error (does the estimate rank atoms correctly?).

    gaussian-atoms check-precision RUN/config.yml [RUN2/config.yml ...] --output docs/uncertainty_check.md
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def check_precision(config: Path) -> dict:
    """One finished run (``config.yml``) whose data have a truth file: its atoms' stated
    precision against their actual errors, per axis and by quartile (module text)."""
    from gaussian_atoms_method.atoms.atom_set import read_atoms
    from gaussian_atoms_method.atoms.matching import match_atoms
    from gaussian_atoms_method.nerfstudio_layer.launch import load_model

    model = load_model(config)
    atoms = model.atoms()
    std, noise = model.position_std_A(atoms)
    truth = read_atoms(model.truth_path)
    pred_idx, true_idx = match_atoms(atoms.positions, truth.positions, 0.75)
    err = atoms.positions[pred_idx] - truth.positions[true_idx]
    s = std[pred_idx]
    total_pred = np.sqrt((s**2).sum(axis=1))
    total_err = np.sqrt((err**2).sum(axis=1))
    quartile = np.digitize(total_pred, np.quantile(total_pred, [0.25, 0.5, 0.75]))
    return {
        "run": str(config.parent),
        "data": str(model.truth_path.parent.name),
        "matched": len(pred_idx),
        "noise": noise,
        "pred_pm": np.median(s, axis=0) * 100,
        "actual_pm": np.sqrt((err**2).mean(axis=0)) * 100,
        "within_1": np.mean(np.abs(err) < s, axis=0),
        "within_2": np.mean(np.abs(err) < 2 * s, axis=0),
        "quartiles": [
            (np.median(total_pred[quartile == q]) * 100, np.sqrt(np.mean(total_err[quartile == q] ** 2)) * 100)
            for q in range(4)
        ],
    }


def precision_table(rows: list[dict]) -> str:
    """The rows of :func:`check_precision` as markdown tables."""
    out = (
        "| data | matched | noise (est.) | axis | predicted std (pm, median) | actual RMS (pm) | actual / predicted "
        "| within 1 std | within 2 std |\n"
    )
    out += "| --- | --- | --- | --- | --- | --- | --- | --- | --- |\n"
    for r in rows:
        for k, axis in enumerate("xyz"):
            lead = f"| {r['data']} | {r['matched']} | {r['noise']:.3g} " if k == 0 else "| | | "
            out += (
                lead + f"| {axis} | {r['pred_pm'][k]:.1f} | {r['actual_pm'][k]:.1f} | "
                f"{r['actual_pm'][k] / r['pred_pm'][k]:.2f} | {r['within_1'][k]:.2f} | {r['within_2'][k]:.2f} |\n"
            )
    out += "\nBy quartile of the predicted 3D precision (median predicted -> actual 3D RMS error, pm):\n\n"
    out += "| data | Q1 | Q2 | Q3 | Q4 |\n| --- | --- | --- | --- | --- |\n"
    for r in rows:
        out += f"| {r['data']} | " + " | ".join(f"{p:.1f} -> {a:.1f}" for p, a in r["quartiles"]) + " |\n"
    return out
