"""The peer benchmark: the Miao group's simulated 208-atom amorphous-Si particle.

Data (../shared/data/asi208, README there): 60 projections of 128 x 128 pixels of 0.195 Å,
single-axis tilts theta = 0:3:177 given as ZYZ Euler angles, at three electron doses, and the
true positions.  Each dose is read straight from the peer's MATLAB files (through
:mod:`dataparsers.readers`), written as a tilt-series directory, reconstructed by
``ns-train gaussian-atoms`` and scored the way the peer scored its own pipeline:

* both atom sets centred on their means, the truth's x and y swapped (the peer's scoring
  script pairs the truth's x with the reconstruction's second array axis);
* the Miao group's iterated global mean shift, then one-to-one pairs within 0.9 Å;
* RMSD = sqrt(sum over x, y, z of the variance of the paired differences).

The peer's pipeline (RESIRE, BM3D, polynomial tracing) finds all 208 within 0.9 Å at about
4.2 pm at dose 1.6e5.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gaussian_atoms_method.atoms.atom_set import AtomSet
from gaussian_atoms_method.atoms.matching import global_shift, match_atoms

DOSE_FILES = {
    "1.6e5": "aSi_2nmFosCetr_Dose1p6e5_cov35pm_ForBM3D.mat",
    "1.6e4": "aSi_2nmFosCetr_Dose1p6e4_cov35pm_ForBM3D.mat",
    "8e3": "aSi_2nmFosCetr_Dose8p0e3_cov35pm_ForBM3D.mat",
}
PEER_MODEL_FILES = {
    "1.6e5": "peer_models/Model_aSi2nm_FoscCenter_Dose1p6e5_cov35pm_BM3D.mat",
    "1.6e4": "peer_models/Model_aSi2nm_FoscCenter_Dose1p6e4_cov35pm_BM3D.mat",
    "8e3": "peer_models/Model_aSi2nm_FoscCenter_Dose8p0e3_cov35pm_BM3D.mat",
}
"""The peer pipeline's own traced atoms at each dose: the rows to beat."""
ANGLES_FILE = "Si_Angle.mat"
TRUTH_FILE = "aSi_208atoms_GT.txt"
PIXEL_SIZE_A = 0.195
MATCH_RADIUS_A = 0.9


def read_peer_truth(path: Path) -> np.ndarray:
    """(N, 3) true positions in Å from the peer's ``type x y z`` text file (``%`` comments)."""
    rows = np.loadtxt(path, comments="%", ndmin=2)
    if rows.shape[1] != 4:
        raise ValueError(f"{path}: expected rows 'type x y z', got {rows.shape[1]} columns")
    return rows[:, 1:4]


def prepare_dose(data_dir: Path, out_dir: Path, dose: str) -> Path:
    """Write one dose as a tilt-series directory (projections, angles, truth in our frame)."""
    from dataparsers.readers import read_angles, read_stack, single_axis_from_euler
    from dataparsers.tilt_series_format import write_tilt_series

    stack = read_stack(data_dir / DOSE_FILES[dose], tilt_index_axis=2)  # MATLAB (H, W, N)
    angles = single_axis_from_euler(read_angles(data_dir / ANGLES_FILE), data_dir / ANGLES_FILE)
    truth = read_peer_truth(data_dir / TRUTH_FILE)
    h, w = stack.projections.shape[1:]
    # RESIRE rotates about voxel n // 2; the truth only matters up to a shift (scored centred).
    return write_tilt_series(
        out_dir / f"dose{dose}",
        stack.projections.astype(np.float32),
        angles,
        PIXEL_SIZE_A,
        truth=AtomSet(positions=truth[:, [1, 0, 2]] - truth.mean(0)[[1, 0, 2]], species=np.array(["Si"] * len(truth))),
        centre_px=(h // 2, w // 2),
        extra={"description": f"aSi-208 peer benchmark, dose {dose} e/A^2, read from {DOSE_FILES[dose]}"},
    )


def read_peer_model(path: Path) -> np.ndarray:
    """(N, 3) positions in Å of the peer's traced model: ``temp_model`` (3 x N, 3x-oversampled
    voxels) converted as the peer converts it, ``(temp_model / 3 - 2) * 0.195``; in the frame
    of our tilt-series directories (the truth's x and y swapped), up to a shift."""
    from dataparsers.readers import _mat_variables

    model = np.asarray(_mat_variables(Path(path))["temp_model"], dtype=np.float64)
    return ((model / 3.0 - 2.0) * PIXEL_SIZE_A).T


def peer_scores(data_dir: Path, dose: str) -> dict | None:
    """The peer pipeline's row at ``dose``, scored like ours (None if its model file is absent)."""
    path = data_dir / PEER_MODEL_FILES[dose]
    if not path.is_file():
        return None
    truth = read_peer_truth(data_dir / TRUTH_FILE)
    return score_like_peer(read_peer_model(path), truth[:, [1, 0, 2]])


def score_like_peer(pred_A: np.ndarray, true_A: np.ndarray, radius_A: float = MATCH_RADIUS_A) -> dict:
    """The peer's scoring (module docstring); positions in Å, any common frame."""
    pred = np.asarray(pred_A, dtype=np.float64) - np.mean(pred_A, axis=0)
    true = np.asarray(true_A, dtype=np.float64) - np.mean(true_A, axis=0)
    pred = pred + global_shift(pred, true, radius_A)
    pi, ti = match_atoms(pred, true, radius_A)
    diff = pred[pi] - true[ti]
    rmsd_pm = float(np.sqrt(diff.var(axis=0).sum()) * 100) if len(pi) > 1 else float("nan")
    return {
        "n_true": len(true),
        "n_pred": len(pred),
        "n_matched": int(len(pi)),
        "tpr": len(pi) / len(true),
        "fp_per_true_atom": (len(pred) - len(pi)) / len(true),
        "rmsd_pm": rmsd_pm,
        "radius_A": radius_A,
    }


@dataclass
class PeerBenchmark:
    data_dir: Path
    output: Path
    doses: tuple[str, ...] = ("1.6e5", "1.6e4", "8e3")
    iterations: int = 3000
    device: str = "cpu"
    flags: tuple[str, ...] = ()
    """Extra ns-train flags (none: the benchmark runs the defaults, which read the counts' noise
    and their one-count floor from the data)."""

    def run(self) -> list[dict]:
        from gaussian_atoms_method.atoms.atom_set import read_atoms
        from gaussian_atoms_method.harness.benchmark import scored_run

        for name in (*(DOSE_FILES[d] for d in self.doses), ANGLES_FILE, TRUTH_FILE):
            if not (self.data_dir / name).is_file():
                raise FileNotFoundError(f"{self.data_dir / name}: not found (the aSi-208 data, ../shared/data/asi208)")
        rows = []
        for dose in self.doses:
            run_dir = self.output / "runs" / f"dose{dose}"
            s = scored_run(
                run_dir / "evaluation.json",
                run_dir,
                lambda dose=dose: prepare_dose(self.data_dir, self.output / "data", dose),
                lambda data, atoms: score_like_peer(atoms.positions, read_atoms(data / "atoms_true.xyz").positions),
                self.iterations,
                self.device,
                self.flags,
            )
            peer = peer_scores(self.data_dir, dose)
            rows.append({"dose": dose, **s, "peer": peer})
            beside = (
                f"; peer {peer['n_matched']}/{peer['n_true']}, FP {peer['n_pred'] - peer['n_matched']}, RMSD "
                f"{peer['rmsd_pm']:.2f} pm"
                if peer
                else ""
            )
            print(
                f"aSi-208 dose {dose}: ours {s['n_matched']}/{s['n_true']} within {s['radius_A']} Å, FP "
                f"{s['n_pred'] - s['n_matched']}, RMSD {s['rmsd_pm']:.2f} pm, {s['seconds']:.0f} s{beside}",
                flush=True,
            )
        self.write(rows)
        return rows

    def write(self, rows: list[dict]) -> None:
        self.output.mkdir(parents=True, exist_ok=True)
        scores = ["n_pred", "n_matched", "tpr", "fp_per_true_atom", "rmsd_pm"]
        fields = ["dose", "n_true", *scores, "seconds", *(f"peer_{k}" for k in scores)]
        with open(self.output / "results.csv", "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
            writer.writeheader()
            writer.writerows([r | {f"peer_{k}": v for k, v in (r.get("peer") or {}).items()} for r in rows])
        lines = [
            "| dose (e/Å²) | method | found (≤ 0.9 Å) | false | RMSD (pm) | time (s) |",
            "| --- | --- | --- | --- | --- | --- |",
        ]
        for r in rows:
            lines.append(
                f"| {r['dose']} | ours | {r['n_matched']}/{r['n_true']} | {r['n_pred'] - r['n_matched']} | "
                f"{r['rmsd_pm']:.2f} | {r['seconds']:.0f} |"
            )
            p = r.get("peer")
            if p:
                lines.append(
                    f"| {r['dose']} | peer (RESIRE, BM3D, tracing) | {p['n_matched']}/{p['n_true']} | "
                    f"{p['n_pred'] - p['n_matched']} | {p['rmsd_pm']:.2f} | |"
                )
        (self.output / "results.md").write_text("\n".join(lines) + "\n")
