"""The start's pair searches on the host and on a device: CLEAN's pairs within the point
response's box and the strongest-first suppression of maxima, at a large particle's size.

    python scripts/studies/benchmark_pair_search.py [--device cuda] [--peaks 97000] [--maxima 395000]
    python scripts/studies/benchmark_pair_search.py --device cuda --data DIR   # also the whole start, twice

Synthetic peaks fill a sphere of 57 Å on 0.25 Å voxels (a 54,000-atom a-Pd's start holds 96,995
candidates), with an 81^3 response (the point response's 10 Å box); the maxima are kept 1 Å
apart.  Each row: the host's k-d tree search against the binned search on ``--device``
(:mod:`gaussian_atoms_method.atoms.voxel_pairs`), twice, with a check that both give the same
result.  ``--data``: a tilt-series directory (e.g. ``gaussian-atoms simulate --particle apd
--scale 1.5 --potential gaussian --tilts limited --noise-std 50``), whose back-projection start
runs on ``--device``, twice (the second warm).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from gaussian_atoms_method.atoms.maxima import suppress_within_device, suppress_within_host  # noqa: E402
from gaussian_atoms_method.atoms.point_response import _response_pairs, clean_peaks, response_pairs_on_device  # noqa: E402


def _sync(device: str) -> None:
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


def timed(fn, device: str):
    _sync(device)
    start = time.perf_counter()
    out = fn()
    _sync(device)
    return out, time.perf_counter() - start


def sphere_points(count: int, radius_vox: float, rng) -> np.ndarray:
    """About ``count`` distinct integer voxels spread uniformly in a sphere, in random order."""
    p = rng.normal(size=(2 * count, 3))
    p *= radius_vox * rng.uniform(0, 1, (len(p), 1)) ** (1 / 3) / np.linalg.norm(p, axis=1, keepdims=True)
    points = np.unique(np.rint(p + radius_vox + 1).astype(np.int64), axis=0)
    return points[rng.permutation(len(points))][:count]


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--peaks", type=int, default=97000, help="CLEAN's candidates")
    parser.add_argument("--maxima", type=int, default=395000, help="maxima to suppress within 1 Å")
    parser.add_argument("--data", type=Path, help="a tilt-series directory: also time its back-projection start")
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    peaks = sphere_points(args.peaks, 230, rng)
    grid = np.indices((81, 81, 81)) - 40
    response, centre = np.exp(-(grid[0] ** 2 + grid[1] ** 2) / 8 - grid[2] ** 2 / 60), np.array([40, 40, 40])
    values = np.sort(rng.uniform(0.5, 10.0, len(peaks)))[::-1]
    maxima = sphere_points(args.maxima, 230, rng)
    heights = rng.uniform(0, 1, len(maxima))
    response_pairs_on_device(peaks[:100], response, centre, args.device)  # the device's first use
    print(f"device: {args.device}; {len(peaks)} peaks, {len(maxima)} maxima", flush=True)
    print("| what | host (s) | device (s) | same result |\n| --- | --- | --- | --- |", flush=True)
    for _ in range(2):
        host, th = timed(lambda: _response_pairs(peaks, response, centre), "cpu")
        dev, td = timed(lambda: response_pairs_on_device(peaks, response, centre, args.device), args.device)
        order = np.lexsort((host[1], host[0]))
        same = all(np.array_equal(a[order], b) for a, b in zip(host, dev))
        print(f"| CLEAN's pair search ({len(host[0]):,} pairs) | {th:.2f} | {td:.2f} | {same} |", flush=True)
        (a, _), th = timed(lambda: clean_peaks(peaks, values, response, centre, 2.0), "cpu")
        (b, _), td = timed(lambda: clean_peaks(peaks, values, response, centre, 2.0, args.device), args.device)
        print(f"| CLEAN ({len(a):,} kept) | {th:.2f} | {td:.2f} | {np.array_equal(a, b)} |", flush=True)
        a, th = timed(lambda: suppress_within_host(maxima * 0.25, np.argsort(-heights, kind="stable"), 1.0), "cpu")
        b, td = timed(
            lambda: suppress_within_device(torch.as_tensor(maxima, device=args.device), heights, 0.25, 1.0),
            args.device,
        )
        print(
            f"| suppression within 1 Å ({len(a):,} kept) | {th:.2f} | {td:.2f} | {np.array_equal(a, b)} |", flush=True
        )
    if args.data is not None:
        from dataparsers.tilt_series_format import load_tilt_series
        from gaussian_atoms_method.atoms.candidates import backprojection_candidates

        series = load_tilt_series(args.data)
        for run in range(2):
            found, seconds = timed(
                lambda: backprojection_candidates(
                    series.projections,
                    series.angles_deg,
                    series.pixel_size_A,
                    series.tilt_axis,
                    series.centre_px,
                    device=args.device,
                    tilt_axis_angle_deg=series.tilt_axis_angle_deg,
                ),
                args.device,
            )
            print(
                f"back-projection start on {args.device} ({'warm' if run else 'first'}): {seconds:.2f} s, {len(found)} "
                f"candidates",
                flush=True,
            )


if __name__ == "__main__":
    main()
