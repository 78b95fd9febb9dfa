"""What each torch operation's first call costs in a process's first ``ga.reconstruct`` on a GPU.

Reads a tilt series into memory, makes torch and the device ready, then profiles one
``ga.reconstruct`` call (``torch.profiler``, host activity).  For each operation: its first
call's host time less the median of its later calls (the first call loads the operation's CUDA
module), and when in the call it came.  Nested operations count in their parents too, so the
total counts some costs twice.

    python scripts/studies/first_call_ops.py --data <series> --device cuda
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict
from pathlib import Path

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True, help="a tilt-series directory")
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--iterations", type=int, default=250)
    parser.add_argument("--rows", type=int, default=40, help="the costliest this many operations")
    args = parser.parse_args()

    import torch
    from torch.profiler import ProfilerActivity, profile

    import gaussian_atoms_method as ga

    series = ga.read_tilt_series(args.data)
    torch.zeros(1, device=args.device).sum().item()
    start = time.perf_counter()
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        ga.reconstruct(
            series,
            device=args.device,
            progress=False,
            max_num_iterations=args.iterations,
            stop_when_converged=False,
            final_refit=False,
        )
    print(f"the call, profiled: {time.perf_counter() - start:.2f} s")
    events = sorted(prof.events(), key=lambda e: e.time_range.start)
    origin = events[0].time_range.start
    first, later, at = {}, defaultdict(list), {}
    for e in events:
        if not e.name.startswith(("aten::", "cu")):
            continue
        if e.name in first:
            later[e.name].append(e.cpu_time_total)
        else:
            first[e.name], at[e.name] = e.cpu_time_total, (e.time_range.start - origin) / 1e6
    cost = {name: (first[name] - (np.median(later[name]) if later[name] else 0.0)) / 1e3 for name in first}
    ranked = sorted(cost, key=cost.get, reverse=True)
    print(f"first calls' extra cost in all: {sum(c for c in cost.values() if c > 0):.0f} ms (nested counted twice)")
    print("| operation | first call's extra (ms) | at (s) | calls |")
    print("| --- | --- | --- | --- |")
    for name in ranked[: args.rows]:
        print(f"| `{name}` | {cost[name]:.1f} | {at[name]:.2f} | {1 + len(later[name])} |")


if __name__ == "__main__":
    main()
