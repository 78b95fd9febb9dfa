"""Projectors on a GPU (or the CPU): agreement with the float64 reference and speed (forward + backward).

Scenes like the Au particle's: Gaussians of 0.6 Å in a 56 Å cube seen on 280 x 280 pixels of
0.25 Å.  For each projector (dense matmul, tiled, gsplat-tiled) and each scene size: the largest
difference from the float64 dense projection (fraction of the image peak) and the time of a
forward + backward pass for 1 view and for all 47 views in one batch (median of 20 after 3
warm-ups, CUDA-synchronised), and the peak GPU memory.  TF32 stays off (it costs 0.6%).

    python3 scripts/studies/benchmark_projectors.py [--sizes 1000 7000 17000 50000 100000] [--output DIR]
    python3 scripts/studies/benchmark_projectors.py --device cpu --sizes 1000 7000 17000 --views 1 --repeats 5
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from gaussian_atoms_method.physics.geometry import detector_axes_from_tilts  # noqa: E402
from gaussian_atoms_method.physics.projector import project_gaussians, project_gaussians_gsplat, project_gaussians_tiled  # noqa: E402

PROJECTORS = {"dense": project_gaussians, "tiled": project_gaussians_tiled, "gsplat": project_gaussians_gsplat}


def scene(n: int, device: str, dtype=torch.float32, pixels: int = 280, pixel_A: float = 0.25):
    g = torch.Generator().manual_seed(n)
    box = pixels * pixel_A
    means = ((torch.rand(n, 3, generator=g) - 0.5) * 0.8 * box).to(device, dtype)
    sigmas = torch.full((n,), 0.6).to(device, dtype)
    amps = (0.5 + torch.rand(n, generator=g)).to(device, dtype)
    axes = torch.tensor(detector_axes_from_tilts(np.arange(-70, 69, 3.0), "y"), dtype=dtype, device=device)
    coords = ((torch.arange(pixels) + 0.5 - pixels / 2) * pixel_A).to(device, dtype)
    return means, sigmas, amps, axes, coords


def _sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def time_pass(project, params, axes, coords, views: int, repeats: int = 20) -> float:
    times = []
    device = params[0].device.type
    for i in range(repeats + 3):
        for p in params:
            p.grad = None
        _sync(device)
        start = time.perf_counter()
        img = project(*params, axes[:views], coords, coords)
        img.abs().mean().backward()
        _sync(device)
        if i >= 3:
            times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1000, 7000, 17000, 50000, 100000])
    parser.add_argument("--projectors", nargs="+", default=list(PROJECTORS))
    parser.add_argument("--output", type=Path, default=Path("outputs/gpu-projectors"))
    parser.add_argument("--device", default="cuda", choices=["cuda", "cpu"])
    parser.add_argument("--views", type=int, nargs="+", default=[1, 47])
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args()
    torch.backends.cuda.matmul.allow_tf32 = False
    torch.backends.cudnn.allow_tf32 = False
    dev = args.device
    if dev == "cpu":
        args.projectors = [p for p in args.projectors if p != "gsplat"]
    rows = []
    for n in args.sizes:
        ref_scene = scene(n, dev, torch.float64)
        reference = (
            project_gaussians(*ref_scene[:3], ref_scene[3][:4], ref_scene[4], ref_scene[4]) if n <= 20000 else None
        )
        for name in args.projectors:
            project = PROJECTORS[name]
            means, sigmas, amps, axes, coords = scene(n, dev)
            params = [t.clone().requires_grad_() for t in (means, sigmas, amps)]
            err = float("nan")
            if reference is not None:
                with torch.no_grad():
                    img = project(*params, axes[:4], coords, coords).double()
                err = float((img - reference).abs().max() / reference.abs().max())
            row = {"gaussians": n, "projector": name, "max_error_of_peak": err}
            for views in args.views:
                if name == "dense" and n * views > 2_000_000:
                    row[f"ms_{views}_views"] = float("nan")  # (47, 280, N) matrices: too much memory
                    continue
                if dev == "cuda":
                    torch.cuda.reset_peak_memory_stats()
                row[f"ms_{views}_views"] = 1e3 * time_pass(project, params, axes, coords, views, args.repeats)
                if dev == "cuda":
                    row[f"peak_GB_{views}_views"] = torch.cuda.max_memory_allocated() / 1e9
            rows.append(row)
            print(json.dumps(row), flush=True)
    args.output.mkdir(parents=True, exist_ok=True)
    name = torch.cuda.get_device_name() if dev == "cuda" else f"CPU, {torch.get_num_threads()} threads"
    (args.output / f"projectors_{dev}.json").write_text(json.dumps({"device": name, "rows": rows}, indent=2))
    head = "| Gaussians | projector | max error / peak | " + " | ".join(f"{v} view(s) (ms)" for v in args.views) + " |"
    lines = [
        f"{name}, torch {torch.__version__}, float32, TF32 off, forward + backward, median of {args.repeats}",
        "",
        head,
        "|" + " --- |" * (3 + len(args.views)),
    ]
    for r in rows:
        times = " | ".join(f"{r.get(f'ms_{v}_views', float('nan')):.2f}" for v in args.views)
        lines.append(f"| {r['gaussians']:,} | {r['projector']} | {r['max_error_of_peak']:.1e} | {times} |")
    (args.output / f"projectors_{dev}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
