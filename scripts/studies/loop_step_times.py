"""Where a warm ``ga.reconstruct``'s training steps go: wall time per step over stretches of the
loop without events, and the time the events between them take.

Runs ``ga.reconstruct`` ``--calls`` times in one process (the first pays the imports and CUDA's
first uses; the later ones are warm) and records when each step begins.  Steps whose time does
not change when the host's work a step shrinks are bound by the device.

    python scripts/studies/loop_step_times.py --data <series> --device cuda --calls 4
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

STRETCHES = ((10, 90), (110, 140), (160, 190), (210, 250))
"""Steps without refines, merges or residual searches between them (the warm-up ends at 200,
the first residual search is at 150, the refines every 100 after the warm-up)."""
EVENTS = ((140, 160), (190, 210))
"""Stretches holding the residual search (150) and the first refine (200)."""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True, help="tilt-series directory")
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--calls", type=int, default=4)
    args = parser.parse_args()

    import gaussian_atoms_method as ga
    from gaussian_atoms_method.engine import training

    begins: dict[int, float] = {}
    own_step = training.FitLoop.train_step

    def timed_step(loop, step, *rest, **options):
        begins[step] = time.perf_counter()
        return own_step(loop, step, *rest, **options)

    training.FitLoop.train_step = timed_step
    series = ga.read_tilt_series(args.data)
    last = max(b for _, b in STRETCHES + EVENTS)
    heads = ["call", "step 1 (s)", "step 250 (s)", *(f"ms/step {a}-{b}" for a, b in STRETCHES)]
    heads += [f"{a}-{b} (s)" for a, b in EVENTS]
    print("| " + " | ".join(heads) + " |")
    print("| --- " * len(heads) + "|")
    for call in range(args.calls):
        begins.clear()
        called = time.perf_counter()
        ga.reconstruct(
            series, device=args.device, progress=False, max_num_iterations=last + 10, stop_when_converged=False,
            final_refit=False,
        )  # fmt: skip
        per = [f"{(begins[b] - begins[a]) / (b - a) * 1000:.2f}" for a, b in STRETCHES]
        events = [f"{begins[b] - begins[a]:.3f}" for a, b in EVENTS]
        cells = [str(call + 1), f"{begins[1] - called:.3f}", f"{begins[250] - called:.3f}", *per, *events]
        print("| " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
