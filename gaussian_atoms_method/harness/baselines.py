"""The voxel baselines end to end: reconstruct (FBP, SART or an INR), trace atoms, write and
score them, as the paper ran its comparisons.  The reconstructions themselves are in
:mod:`gaussian_atoms_method.physics.reconstruction` and :mod:`.inr`; the tracing in
:mod:`.tracing`."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from dataparsers.tilt_series_format import load_tilt_series
from gaussian_atoms_method.atoms.atom_set import AtomSet, write_atoms
from gaussian_atoms_method.harness.evaluation import evaluate_atoms, load_reference, summary_line
from gaussian_atoms_method.harness.tracing import trace_atoms
from gaussian_atoms_method.physics.reconstruction import reconstruct

METHODS = ("fbp", "sart", "inr")


def run_baseline(
    data: Path,
    output: Path,
    method: str = "sart",
    sart_iterations: int = 1,
    inr_steps: int = 10000,
    device: str = "cpu",
    min_distance_A: float = 2.0,
    threshold_scale: float = 1.0,
    save_volume: bool = False,
) -> dict | None:
    """Reconstruct the tilt series in ``data`` with ``method``, trace atoms in the volume and
    write ``atoms.xyz``, ``atoms.csv`` (and ``volume.npy``) to ``output``.

    With a truth file the atoms are scored (TPR, false positives, RMSD, volume SSIM; also
    written to ``evaluation.json``) and the scores returned; otherwise None.  ``seconds`` in
    the scores is the reconstruction and tracing time.
    """
    if method not in METHODS:
        raise ValueError(f"unknown baseline {method!r}; expected one of {', '.join(METHODS)}")
    series = load_tilt_series(data)
    start = time.perf_counter()
    if method == "inr":
        from gaussian_atoms_method.harness.inr import fit_inr

        vol = fit_inr(
            series.projections,
            series.angles_deg,
            series.pixel_size_A,
            series.tilt_axis,
            series.centre_px,
            inr_steps,
            device=device,
            tilt_axis_angle_deg=series.tilt_axis_angle_deg,
        )
    else:
        vol = reconstruct(
            series.projections,
            series.angles_deg,
            series.pixel_size_A,
            method,
            series.tilt_axis,
            series.centre_px,
            sart_iterations,
            tilt_axis_angle_deg=series.tilt_axis_angle_deg,
        )
    idx, _ = trace_atoms(vol.data, vol.spacing_A, min_distance_A, threshold_scale)
    seconds = time.perf_counter() - start
    atoms = AtomSet(vol.index_to_A(idx) + series.origin_A)
    output.mkdir(parents=True, exist_ok=True)
    write_atoms(atoms, output / "atoms.xyz")
    write_atoms(atoms, output / "atoms.csv")
    if save_volume:
        np.save(output / "volume.npy", vol.data.astype(np.float32))
    if series.truth_path is None:
        print(f"{method}: {len(atoms)} atoms traced in {seconds:.1f} s")
        return None
    _, truth, reference, voxel = load_reference(data, series)
    pred_volume = vol.resample(reference.shape, voxel) if reference is not None else None
    scores = evaluate_atoms(atoms, truth, reference_volume=reference, voxel_size_A=voxel, pred_volume=pred_volume)
    scores["seconds"] = seconds
    (output / "evaluation.json").write_text(json.dumps(scores, indent=2) + "\n")
    print(summary_line(scores, f"{method} ({seconds:.1f} s)"))
    return scores
