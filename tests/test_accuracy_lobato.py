"""CI guards accuracy on independent physics: a Lobato (abTEM) simulation, not our Gaussian
forward model, trained with the defaults through the front door (``gaussian-atoms train``).

The particle: the paper's Au particle cut to scale 0.35 (312 atoms, 2.88 Å apart), limited
tilts (-70:3:68, 47 views), 0.5 Å probe blur, additive noise 200 V·Å (peak-to-noise 6.7).
Measured with the defaults (seeds 0, 1, 2; each converged at step 600, about 12 s):
TPR 1.000 / 1.000 / 1.000, false positives 0 / 0 / 0, RMSD 9.7 / 10.1 / 10.0 pm.

Tolerances: TPR >= 0.99 and <= 0.01 false per atom (at most 3 of 312 atoms missed or
invented: atoms 2.88 Å apart at peak-to-noise 6.7 are unambiguous, so any more is a
regression); RMSD <= 15 pm: the run's own Cramér-Rao precision is about 8 pm in 3D
(x 4.5, y 3.5, z 5.8 pm), and on Lobato data the actual error has been measured at 1.1-1.9
times that bound (docs/results.md, the uncertainty check), so 15 pm = 1.9 x 8 pm.
"""

import json
import subprocess
import sys
from pathlib import Path

BIN = Path(sys.executable).parent


def test_lobato_au_trains_to_the_measured_accuracy(tmp_path):
    data, out = tmp_path / "data", tmp_path / "out"
    sim = subprocess.run(
        [
            str(BIN / "gaussian-atoms"),
            "simulate",
            "--particle",
            "au",
            "--scale",
            "0.35",
            "--tilts",
            "limited",
            "--noise-std",
            "200",
            "--seed",
            "0",
            "--output",
            str(data),
            "--no-save-volume",
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert sim.returncode == 0, sim.stderr[-2000:]
    train = subprocess.run(
        [
            str(BIN / "gaussian-atoms"),
            "train",
            "--machine.device-type",
            "cpu",
            "--vis",
            "tensorboard",
            "--output-dir",
            str(out),
            "--experiment-name",
            "lobato",
            "--timestamp",
            "run",
            "tilt-series",
            "--data",
            str(data),
        ],
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert train.returncode == 0, train.stdout[-2000:] + train.stderr[-2000:]
    scores = json.loads((out / "lobato" / "gaussian-atoms" / "run" / "evaluation.json").read_text())
    assert scores["n_true"] == 312
    assert scores["tpr"] >= 0.99 and scores["fp_per_true_atom"] <= 0.01, scores
    assert scores["rmsd_pm"] <= 15.0, scores
