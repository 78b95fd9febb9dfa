"""Scaling table: time per training iteration and memory against the number of atoms.

For each N, a particle of Au density (0.059 atoms/Å^3) holding N atoms needs a detector that
spans it: side = particle diameter + 10 Å at 0.25 Å pixels (the 6,679-atom Au particle: 280
pixels).  A 47-view limited tilt series of that size (random values: the cost of an iteration
does not depend on them) is read by the tilt-series dataparser, the model holds N Gaussians,
and an iteration is what ns-train does per step: render one view, L1 loss, backward, Adam
step, parameter clamping (densify / prune / merge run every 100 steps and are timed by
scripts/studies/benchmark_merge.py).  Reported: median seconds per iteration over 30 iterations after
5 warm-up ones, and peak memory (GPU: max allocated; CPU: the process's peak RSS).

    python scripts/studies/scaling.py --device cuda --atoms 1000 7000 17000 50000 100000 \
        --output outputs/scaling_cuda.md
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

AU_DENSITY = 0.059  # atoms per Å^3 (fcc Au, a = 4.08 Å)


def detector_pixels(n_atoms: int, pixel_size_A: float = 0.25) -> int:
    radius = (3 * n_atoms / (4 * np.pi * AU_DENSITY)) ** (1 / 3)
    return int(np.ceil((2 * radius + 10.0) / pixel_size_A))


def time_iterations(n_atoms: int, device: str, iterations: int = 30, warmup: int = 5) -> dict:
    from nerfstudio.engine.optimizers import Optimizers

    from dataparsers.tilt_series_dataparser import TiltSeriesDataParserConfig
    from dataparsers.tilt_series_format import write_tilt_series
    from gaussian_atoms_method.engine.rendering import projector_name
    from gaussian_atoms_method.harness.simulate import parse_tilts
    from gaussian_atoms_method.nerfstudio_layer.config import gaussian_atoms_trainer_config
    from gaussian_atoms_method.nerfstudio_layer.model import GaussianAtomsModelConfig

    side = detector_pixels(n_atoms)
    angles = parse_tilts("limited")
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        write_tilt_series(Path(tmp), rng.uniform(0, 1, (len(angles), side, side)).astype(np.float32), angles, 0.25)
        outputs = TiltSeriesDataParserConfig(data=Path(tmp)).setup().get_dataparser_outputs("train")
    radius_norm = 0.5 * (side * 0.25 - 10.0) / (side * 0.25)
    model = GaussianAtomsModelConfig(
        init="random", num_random=n_atoms, init_extent=2 * radius_norm / np.sqrt(3), coarse_steps=0
    ).setup(scene_box=outputs.scene_box, num_train_data=len(angles), metadata=outputs.metadata)
    model.to(device)
    optimizers = Optimizers(gaussian_atoms_trainer_config().optimizers, model.get_param_groups())
    cameras = outputs.cameras.to(device)
    targets = [outputs.metadata["projections"][v][..., None].to(device) for v in range(len(angles))]
    if device == "cuda":
        torch.cuda.reset_peak_memory_stats()
    times = []
    for step in range(warmup + iterations):
        start = time.perf_counter()
        optimizers.zero_grad_all()
        v = step % len(angles)
        loss = model.get_loss_dict(model.get_outputs(cameras[v : v + 1]), {"image": targets[v]})["main_loss"]
        loss.backward()
        optimizers.optimizer_step_all()
        model.density.clamp(model.gauss_params)
        if device == "cuda":
            torch.cuda.synchronize()
        if step >= warmup:
            times.append(time.perf_counter() - start)
    return {
        "atoms": n_atoms,
        "detector": side,
        "s_per_iter": float(np.median(times)),
        "gpu_GB": torch.cuda.max_memory_allocated() / 1e9 if device == "cuda" else float("nan"),
        "rss_GB": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6,
        "projector": projector_name(model.config.projector, torch.device(device)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    parser.add_argument("--atoms", type=int, nargs="+", default=[1000, 7000, 17000, 50000, 100000])
    parser.add_argument("--output", type=Path, default=None)
    args = parser.parse_args()
    torch.backends.cuda.matmul.allow_tf32 = False  # the projector's matmuls need full float32
    name = torch.cuda.get_device_name() if args.device == "cuda" else f"CPU, {torch.get_num_threads()} threads"
    lines = [
        f"Device: {name}",
        "",
        "| atoms | detector (px) | projector | s / iteration | iterations / s | peak GPU memory (GB) | peak RSS (GB) |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for n in args.atoms:
        r = time_iterations(n, args.device)
        lines.append(
            f"| {r['atoms']} | {r['detector']} | {r['projector']} | {r['s_per_iter']:.4f} | {1 / r['s_per_iter']:.1f} "
            f"| {r['gpu_GB']:.2f} | {r['rss_GB']:.2f} |"
        )
        print(lines[-1], flush=True)
    text = "\n".join(lines) + "\n"
    print(text)
    if args.output:
        args.output.write_text(text)


if __name__ == "__main__":
    main()
