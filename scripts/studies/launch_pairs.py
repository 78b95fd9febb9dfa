"""Time from launch to the accuracy target of ``gaussian-atoms train``, for two checkouts in
alternated pairs on one machine, beside ``import torch`` (with the device's first use).

The target is the benchmarks' (TPR >= 0.99, FP <= 0.01 per true atom within 0.75 Å), read from
the run's snapshots every 50 steps, their own cost subtracted; the time counts from the launch
of the process.  Compares two code versions where a speed target says "no later than today":
check out the earlier one beside this one (``git worktree add ../old REV``) and give both.

    python scripts/studies/launch_pairs.py DATA . ../old --device cuda --pairs 3
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path


def torch_import_s(device: str) -> float:
    """Seconds for ``import torch`` and the device's first use, in a fresh interpreter."""
    use = "torch.zeros(1, device='cuda').sum().item()" if device == "cuda" else "torch.zeros(1).sum().item()"
    start = time.time()
    subprocess.run([sys.executable, "-c", f"import torch; {use}"], check=True)
    return time.time() - start


def time_to_target(root: Path, data: Path, device: str, steps: int, out: Path):
    """(step, seconds from launch, TPR, FP per atom, RMSD pm) of the first snapshot at the target
    of a ``gaussian-atoms train`` run of checkout ``root`` on ``data``; None if none reached it."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")])}
    launch = time.time()
    subprocess.run(
        [sys.executable, "-m", "gaussian_atoms_method.cli", "train", "--machine.device-type", device,
         "--vis", "tensorboard", "--output-dir", str(out), "--experiment-name", "pair", "--timestamp", "run",
         "--max-num-iterations", str(steps), "--pipeline.model.snapshot-every", "50", "tilt-series", "--data",
         str(data)],
        cwd=root, env=env, check=True, capture_output=True,
    )  # fmt: skip
    from dataparsers.tilt_series_format import load_tilt_series
    from gaussian_atoms_method.atoms.atom_set import read_atoms
    from gaussian_atoms_method.atoms.matching import score_atoms
    from gaussian_atoms_method.engine.results import read_snapshot_times

    truth = read_atoms(load_tilt_series(data).truth_path)
    snapshots = out / "pair" / "gaussian-atoms" / "run" / "snapshots"
    rows, _ = read_snapshot_times(snapshots)
    for step, when, _, _ in rows:
        scores = score_atoms(read_atoms(snapshots / f"step-{step:06d}.csv").positions, truth.positions)
        if scores["tpr"] >= 0.99 and scores["fp_per_true_atom"] <= 0.01:
            return (
                step,
                round(when - launch, 2),
                scores["tpr"],
                round(scores["fp_per_true_atom"], 4),
                round(scores["rmsd_pm"], 1),
            )
    return None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data", type=Path, help="a tilt-series directory with its truth")
    parser.add_argument("roots", type=Path, nargs=2, help="two checkouts: this one and the one to compare")
    parser.add_argument("--device", choices=("cpu", "cuda"), default="cuda")
    parser.add_argument("--pairs", type=int, default=3)
    parser.add_argument("--steps", type=int, default=600, help="--max-num-iterations of each run")
    parser.add_argument("--output", type=Path, default=Path("outputs/launch_pairs"))
    args = parser.parse_args()
    print("import torch + first use (s):", [round(torch_import_s(args.device), 2) for _ in range(3)])
    output = args.output / time.strftime("%Y-%m-%d_%H%M%S")  # snapshots append to their times.csv: a fresh place
    for pair in range(args.pairs):
        for k, root in enumerate(args.roots):
            found = time_to_target(root.resolve(), args.data.resolve(), args.device, args.steps,
                                   (output / f"{pair}-{k}").resolve())  # fmt: skip
            print(f"{root}: pair {pair}: (step, s from launch, TPR, FP/atom, RMSD pm) {found}", flush=True)
    print("import torch + first use (s):", [round(torch_import_s(args.device), 2) for _ in range(2)])


if __name__ == "__main__":
    main()
