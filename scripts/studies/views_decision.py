"""How steady ``--pipeline.model.views-per-step auto``'s choice is: the projector's forward and
backward time for 1, 2, 4 and 8 views, and the views auto picks in repeated decisions, for a
number of Gaussians on a square detector (:func:`gaussian_atoms_method.engine.step_views.auto_views_per_step`).

    python scripts/studies/views_decision.py --gaussians 10438 --pixels 271 --decisions 30

A choice that moves between decisions sits near ``STEP_COST_RATIO``: runs of the same data
then take different numbers of steps (docs/performance.md, several views per step).
"""

from __future__ import annotations

import argparse
import collections
import time

import numpy as np
import torch

from gaussian_atoms_method.engine.rendering import projector_for, synchronise
from gaussian_atoms_method.engine.step_views import STEP_COST_RATIO, auto_views_per_step, probe_scene


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--gaussians", type=int, default=10438, help="Gaussians in the probe scene (default: the Au start's)"
    )
    parser.add_argument("--pixels", type=int, default=271, help="detector side, pixels")
    parser.add_argument("--views", type=int, default=47, help="views in the series")
    parser.add_argument("--decisions", type=int, default=30, help="auto's decisions to repeat")
    parser.add_argument("--calls", type=int, default=30, help="timed calls per batch size")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = parser.parse_args()
    device = torch.device(args.device)
    axis = torch.arange(args.pixels, device=device, dtype=torch.float32) - 0.5 * (args.pixels - 1)
    projector = projector_for("auto", device)
    print("| views | least (ms) | median (ms) | least / one view's |")
    print("| --- | --- | --- | --- |")
    one = None
    for views in (1, 2, 4, 8):
        means, sigmas, amplitudes, detector = probe_scene(args.gaussians, views, axis, axis)
        times = []
        for _ in range(args.calls + 1):
            synchronise(device)
            start = time.perf_counter()
            projector(means, sigmas, amplitudes, detector, axis, axis).square().sum().backward()
            synchronise(device)
            times.append(1e3 * (time.perf_counter() - start))
        least, median = min(times[1:]), float(np.median(times[1:]))
        one = one or least
        print(f"| {views} | {least:.3f} | {median:.3f} | {least / one:.2f} |")
    picks = collections.Counter(
        auto_views_per_step(projector, args.gaussians, args.views, axis, axis) for _ in range(args.decisions)
    )
    print(
        f"\nauto's views in {args.decisions} decisions (ratio {STEP_COST_RATIO:g}): "
        + ", ".join(f"{v}: {n}" for v, n in sorted(picks.items()))
    )


if __name__ == "__main__":
    main()
