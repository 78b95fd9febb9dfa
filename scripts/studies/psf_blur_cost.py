"""The point-spread function's cost a step on a GPU, by FFT and by separable matrices.

Forward and backward through both of :mod:`gaussian_atoms_method.physics.psf`'s ways (float32,
8 views, the package's kernel widths, 0.35 Å pixels, eager), at several detector sides, and
cuFFT's first use in the process: the measurement behind ``MATRIX_BLUR_MAX_SIDE_PX``.

    python scripts/studies/psf_blur_cost.py
"""

from __future__ import annotations

import argparse
import sys
import time


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sides", type=int, nargs="+", default=[128, 200, 271, 400, 600, 800])
    parser.add_argument("--views", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=50)
    args = parser.parse_args()
    import torch

    from gaussian_atoms_method.physics.psf import KERNEL_WIDTHS_A, apply_kernel_by_fft, apply_kernel_by_matrices

    if not torch.cuda.is_available():
        sys.exit("psf_blur_cost.py: torch sees no CUDA device here; run it on a GPU machine")
    torch.zeros(1, device="cuda")
    torch.backends.cuda.matmul.allow_tf32 = False
    spacing, widths = 0.35, tuple(KERNEL_WIDTHS_A)

    def weights():
        return torch.full((len(widths),), 0.1, device="cuda", requires_grad=True)

    def step(apply, images, w):
        apply(images, spacing, widths, w).sum().backward()

    small = torch.rand(args.views, 64, 64, device="cuda", requires_grad=True)
    start = time.perf_counter()
    step(apply_kernel_by_fft, small, weights())
    torch.cuda.synchronize()
    print(f"cuFFT's first use (forward and backward): {1000 * (time.perf_counter() - start):.0f} ms")

    def per_step_ms(apply, side):
        images, w = torch.rand(args.views, side, side, device="cuda", requires_grad=True), weights()
        for _ in range(3):
            step(apply, images, w)
        torch.cuda.synchronize()
        start = time.perf_counter()
        for _ in range(args.repeats):
            step(apply, images, w)
        torch.cuda.synchronize()
        return 1000 * (time.perf_counter() - start) / args.repeats

    print("| detector side (px) | FFT, forward and backward (ms) | separable matrices (ms) |")
    print("| --- | --- | --- |")
    for side in args.sides:
        fft, matrices = per_step_ms(apply_kernel_by_fft, side), per_step_ms(apply_kernel_by_matrices, side)
        print(f"| {side} | {fft:.3f} | {matrices:.3f} |", flush=True)


if __name__ == "__main__":
    main()
