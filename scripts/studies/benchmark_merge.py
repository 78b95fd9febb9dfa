"""Time one cluster merge (k-d tree pairs, connected components, scatter means) at 10k-1M Gaussians.

The scene imitates a fit mid-run: atoms on an fcc Au lattice (2.88 Å apart) in a sphere, and a
fraction of them carrying a second Gaussian within 0.3 Å (a duplicate the merge must fold in).
Prints a Markdown table and writes it to ``outputs/merge_timing.md``.

    python scripts/studies/benchmark_merge.py [--sizes 10000 100000 1000000] [--threshold-A 0.7]
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import numpy as np
import torch

from gaussian_atoms_method.atoms.merge import cluster_labels, merged_values


def scene(n_gaussians: int, duplicate_fraction: float, rng: np.random.Generator) -> np.ndarray:
    n_atoms = int(round(n_gaussians / (1 + duplicate_fraction)))
    a = 4.078  # Au lattice constant, Å
    basis = np.array([[0, 0, 0], [0.5, 0.5, 0], [0.5, 0, 0.5], [0, 0.5, 0.5]]) * a
    side = int(np.ceil((n_atoms / 4) ** (1 / 3))) + 2
    grid = np.stack(np.meshgrid(*[np.arange(side)] * 3, indexing="ij"), -1).reshape(-1, 3) * a
    lattice = (grid[:, None, :] + basis[None]).reshape(-1, 3)
    lattice = lattice[np.argsort(np.linalg.norm(lattice - lattice.mean(0), axis=1))[:n_atoms]]
    dup = lattice[rng.choice(n_atoms, n_gaussians - n_atoms, replace=False)]
    dup = dup + rng.normal(scale=0.3 / np.sqrt(3), size=dup.shape)
    return np.concatenate([lattice, dup])


def time_merge(positions: np.ndarray, threshold_A: float, repeats: int) -> tuple[float, float, int]:
    n = len(positions)
    means = torch.as_tensor(positions, dtype=torch.float32)
    sigmas, amps = torch.full((n,), 0.6), torch.ones(n)
    best_labels, best_total = np.inf, np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        labels, n_clusters = cluster_labels(positions, threshold_A)
        t1 = time.perf_counter()
        merged_values(means, sigmas, amps, torch.as_tensor(labels), n_clusters)
        t2 = time.perf_counter()
        best_labels, best_total = min(best_labels, t1 - t0), min(best_total, t2 - t0)
    return best_labels, best_total, n_clusters


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000, 1_000_000])
    parser.add_argument("--threshold-A", type=float, default=0.7)
    parser.add_argument("--duplicate-fraction", type=float, default=0.05)
    parser.add_argument("--output", type=Path, default=Path("outputs/merge_timing.md"))
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    machine = f"{platform.processor() or platform.machine()}, {torch.get_num_threads()} torch threads"
    lines = [
        f"Merge cost, threshold {args.threshold_A} Å, {args.duplicate_fraction:.0%} of atoms duplicated; best of 3; "
        f"{machine}.",
        "",
        "| Gaussians | clusters | k-d tree + components (s) | whole merge (s) |",
        "| --- | --- | --- | --- |",
    ]
    for n in args.sizes:
        positions = scene(n, args.duplicate_fraction, rng)
        t_labels, t_total, n_clusters = time_merge(positions, args.threshold_A, repeats=3)
        lines.append(f"| {n:,} | {n_clusters:,} | {t_labels:.3f} | {t_total:.3f} |")
        print(lines[-1], flush=True)
    text = "\n".join(lines) + "\n"
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
