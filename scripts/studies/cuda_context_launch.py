"""What making CUDA's context in a thread while torch imports takes off a launch.

Alternates fresh processes that import torch and make their first CUDA tensor, with
:func:`gaussian_atoms_method.launch.cuda_context.begin` called first ("early") and without
("plain"), and prints when torch's import returned, how long CUDA then took to be ready, and
when it was ready from launch.  Needs an NVIDIA GPU.

    python scripts/studies/cuda_context_launch.py --runs 6
"""

from __future__ import annotations

import argparse
import subprocess
import sys

CHILD = """
import sys, time
t0 = time.perf_counter()
if sys.argv[1] == "early":
    from gaussian_atoms_method.launch import cuda_context
    cuda_context.begin()
import torch
t1 = time.perf_counter()
torch.zeros(1, device="cuda")
torch.cuda.synchronize()
t2 = time.perf_counter()
print(f"{t1 - t0:.2f} {t2 - t1:.2f} {t2 - t0:.2f}")
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=6, help="alternated pairs of launches")
    args = parser.parse_args()
    print("| run | context | import torch (s) | CUDA ready after it (s) | ready from launch (s) |")
    print("| --- | --- | --- | --- | --- |")
    for run in range(1, args.runs + 1):
        for mode in ("early", "plain"):
            out = subprocess.run([sys.executable, "-c", CHILD, mode], capture_output=True, text=True, check=True)
            imported, after, ready = out.stdout.split()
            print(f"| {run} | {mode} | {imported} | {after} | {ready} |", flush=True)


if __name__ == "__main__":
    main()
