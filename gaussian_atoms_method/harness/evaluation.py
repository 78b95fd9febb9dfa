"""One scoring entry point for every method: atoms against the truth, and the volume SSIM."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from gaussian_atoms_method.atoms.atom_set import AtomSet
from gaussian_atoms_method.atoms.evidence import evidence_scores
from gaussian_atoms_method.atoms.matching import score_atoms
from gaussian_atoms_method.harness.metrics import volume_ssim, voxelise_gaussians


def evaluate_atoms(
    pred: AtomSet,
    truth: AtomSet,
    radius_A: float = 0.75,
    mean_shift: bool = False,
    reference_volume: np.ndarray | None = None,
    voxel_size_A: float | None = None,
    origin_A=(0.0, 0.0, 0.0),
    pred_volume: np.ndarray | None = None,
    true_counted: np.ndarray | None = None,
) -> dict:
    """Scores of predicted atoms (and of a volume) against the truth.

    Parameters
    ----------
    pred, truth : AtomSet (positions in the same frame, Å)
    radius_A, mean_shift : see :func:`.metrics.score_atoms`
    reference_volume : (n, n, n) array, optional
        The true potential blurred like the data, voxel ``i`` centred at
        ``(i - (n - 1) / 2) * voxel_size_A + origin_A``.  With it, ``ssim`` is reported: of
        ``pred_volume`` if given (a voxel method's reconstruction on the same grid), else of
        the predicted Gaussians voxelised on that grid.
    true_counted : (T,) bool array, optional
        The true atoms scored (:func:`~gaussian_atoms_method.atoms.matching.score_atoms`): those
        in the field the run saw, of a truth wider than it.
    """
    species_known = pred.species is not None and truth.species is not None and not np.all(pred.species == "X")
    scores = score_atoms(
        pred.positions,
        truth.positions,
        radius_A,
        mean_shift,
        pred.species if species_known else None,
        truth.species if species_known else None,
        true_counted,
    )
    if pred.proven is not None and len(pred):
        scores.update(evidence_scores(pred, truth, radius_A, mean_shift, truth_counted=true_counted))
    if reference_volume is not None:
        if pred_volume is None:
            if pred.sigmas is None or pred.amplitudes is None:
                raise ValueError("SSIM needs the predicted atoms' sigma_A and amplitude, or a predicted volume")
            pred_volume = voxelise_gaussians(
                pred.positions - np.asarray(origin_A),
                pred.sigmas,
                pred.amplitudes,
                voxel_size_A,
                reference_volume.shape,
            )
        scores.update(volume_ssim(pred_volume, reference_volume))
    return scores


def summary_line(scores: dict, label: str = "") -> str:
    """One line: TPR, false positives per atom, RMSD (and SSIM)."""
    parts = [
        f"TPR {scores['tpr']:.4f}",
        f"FP/atom {scores['fp_per_true_atom']:.4f}",
        f"RMSD {scores['rmsd_pm']:.1f} pm",
        f"{scores['n_pred']} predicted / {scores['n_true']} true"
        + (f" ({scores['n_true_uncounted']} beyond the field not scored)" if scores.get("n_true_uncounted") else ""),
    ]
    if "ssim" in scores:
        parts.append(f"SSIM {scores['ssim']:.3f} (range {scores['ssim_data_range']:.3g})")
    if "species_accuracy" in scores:
        parts.append(f"species {scores['species_accuracy']:.3f}")
    if "proven" in scores:
        parts.append(f"{scores['proven']} proven, {scores['open']} open, {scores['depth_open']} open in depth")
    if "coverage_95_xyz" in scores:
        parts.append(
            "95% intervals hold x/y/z "
            + "/".join(f"{c:.2f}" for c in scores["coverage_95_xyz"])
            + f", depth {scores['depth_coverage_95']:.2f}"
            + (
                "; the error they do not hold (for --pipeline.model.precision-floor-A on a real run of this "
                "experiment) " + " ".join(f"{f:.3f}" for f in scores["precision_floor_A"]) + " Å"
                if "precision_floor_A" in scores
                else ""
            )
        )
    if scores.get("open_share_of_disagreement") is not None:
        parts.append(f"open atoms hold {scores['open_share_of_disagreement']:.0%} of the disagreement")
    return (f"{label}: " if label else "") + ", ".join(parts)


def inside_footprint(positions_A: np.ndarray, series, margin_A: float) -> np.ndarray:
    """(N,) bool: positions (Å, the series' truth frame) at least ``margin_A`` inside the
    detector's footprint at zero tilt (rows along x, columns along y, about ``centre_px``).

    Where a film goes on past the detector, whether a Gaussian at the field's edge is reported
    as an atom turns on its position error, and an atom there is seen by only some views:
    scoring the interior, as the Ta film's authors score their sub-areas, measures the method."""
    if series.tilt_axis_angle_deg:
        raise ValueError(
            "--interior-A: the footprint of a detector turned in its plane (tilt_axis_angle_deg) is not supported"
        )
    rel = np.asarray(positions_A, dtype=np.float64)[:, :2] - np.asarray(series.origin_A)[:2]
    px, (h, w), (cr, cc) = series.pixel_size_A, series.image_shape, series.centre_px
    low = np.array([(-0.5 - cr) * px, (-0.5 - cc) * px]) + margin_A
    high = np.array([(h - 0.5 - cr) * px, (w - 0.5 - cc) * px]) - margin_A
    return np.all((rel >= low) & (rel <= high), axis=1)


def load_reference(data: Path, series=None):
    """What a tilt-series directory holds for scoring.

    Returns ``(series, truth AtomSet, reference volume or None, its voxel size or None)``;
    pass ``series`` when it is already loaded, so the projections are not read twice.
    """
    from dataparsers.tilt_series_format import MANIFEST, load_tilt_series
    from gaussian_atoms_method.atoms.atom_set import read_atoms

    data = Path(data)
    if series is None:
        series = load_tilt_series(data)
    if series.truth_path is None:
        raise ValueError(f"{data / MANIFEST}: names no 'truth' file to score against")
    manifest = json.loads((data / MANIFEST).read_text())
    volume = np.load(data / manifest["volume"]) if "volume" in manifest else None
    return series, read_atoms(series.truth_path), volume, manifest.get("volume_voxel_size_A")
