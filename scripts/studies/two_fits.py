"""Two fits sharing one machine: the time of one `gaussian-atoms train` alone and of two at once.

    python scripts/studies/two_fits.py --data data/demo [--env NAME=VALUE ...]

Runs the fit of ``--data`` alone, then two of it at once (each in its own output directory),
and prints each wall time and the ratio to the lone run.  ``--env`` sets a variable in the
fits' environment (``OMP_WAIT_POLICY=ACTIVE`` to compare with OpenMP's spinning workers).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def fit(data: Path, out: Path, env: dict) -> subprocess.Popen:
    command = [sys.executable, "-m", "gaussian_atoms_method.cli", "train", "--machine.device-type", "cpu"]
    command += ["--vis", "tensorboard", "--output-dir", str(out), "tilt-series", "--data", str(data)]
    return subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)


def timed(processes: list[subprocess.Popen], start: float) -> list[float]:
    ends = []
    for p in processes:
        if p.wait() != 0:
            raise SystemExit(f"a fit failed (exit {p.returncode})")
        ends.append(time.perf_counter() - start)
    return ends


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=Path("data/demo"))
    parser.add_argument("--env", action="append", default=[])
    args = parser.parse_args()
    env = {**os.environ, **dict(e.split("=", 1) for e in args.env)}
    with tempfile.TemporaryDirectory() as work:
        start = time.perf_counter()
        (alone,) = timed([fit(args.data, Path(work) / "alone", env)], start)
        start = time.perf_counter()
        both = timed([fit(args.data, Path(work) / f"shared{i}", env) for i in range(2)], start)
    print(f"cores {len(os.sched_getaffinity(0))}, environment {args.env or 'as given'}")
    print("| fit | wall (s) | times alone |\n| --- | --- | --- |")
    print(f"| alone | {alone:.1f} | 1.00 |")
    for i, t in enumerate(both):
        print(f"| two at once, fit {i + 1} | {t:.1f} | {t / alone:.2f} |")


if __name__ == "__main__":
    main()
