"""The cold and warm cost of the first use of each CUDA library a run calls into.

Run in a fresh process on a GPU machine: ``import torch`` and the device's first use are timed,
then each operation twice (cold, then warm), synchronised, in this order: cuFFT, cuSPARSE,
cuBLAS, max-pooling, sort, cuDNN (a 3D convolution), autograd with fused Adam, cuSOLVER, cdist
and a CUDA graph's capture.  The order matters: an operation may load what a later one uses.

    python scripts/studies/cuda_first_use.py
"""

from __future__ import annotations

import argparse
import sys
import time


def main() -> None:
    argparse.ArgumentParser(description=__doc__.split("\n\n")[0]).parse_args()
    start = time.perf_counter()
    import torch

    if not torch.cuda.is_available():
        sys.exit("cuda_first_use.py: torch sees no CUDA device here; run it on a GPU machine")
    torch.zeros(1, device="cuda").sum().item()
    torch.cuda.synchronize()
    print(f"import torch and the device's first use: {time.perf_counter() - start:.2f} s")
    dev = "cuda"
    rows = []

    def timed(name, f):
        costs = []
        for _ in range(2):
            t = time.perf_counter()
            f()
            torch.cuda.synchronize()
            costs.append(1000 * (time.perf_counter() - t))
        rows.append((name, *costs))

    sinograms = torch.ones(40, 271, 300, device=dev, dtype=torch.float64)
    timed("cuFFT (rfft, irfft)", lambda: torch.fft.irfft(torch.fft.rfft(sinograms, n=512, dim=-1), n=512, dim=-1))
    sparse = torch.eye(1000, device=dev).to_sparse_csr()
    dense = torch.ones(1000, 271, device=dev)
    timed("cuSPARSE (CSR @ dense)", lambda: sparse @ dense)
    square = torch.ones(500, 500, device=dev)
    timed("cuBLAS (matmul)", lambda: square @ square)
    volume = torch.ones(1, 1, 100, 100, 100, device=dev)
    timed("max_pool3d", lambda: torch.nn.functional.max_pool3d(volume, 3, 1, 1))
    timed("sort", lambda: volume.reshape(-1).sort())
    kernel = torch.ones(1, 1, 3, 3, 3, device=dev)
    timed("cuDNN (conv3d)", lambda: torch.nn.functional.conv3d(volume, kernel, padding=1))
    params = [torch.ones(300, 3, device=dev, requires_grad=True) for _ in range(4)]
    optimiser = torch.optim.Adam(params, lr=1e-3, fused=True)

    def adam():
        sum((p.exp() ** 2).sum() for p in params).backward()
        optimiser.step()
        optimiser.zero_grad()

    timed("autograd + fused Adam", adam)
    small = torch.eye(3, device=dev) * 2
    timed("cuSOLVER (solve)", lambda: torch.linalg.solve(small, small[:, :2]))
    timed("cdist", lambda: torch.cdist(params[0], params[1]))

    def capture():
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):
            square @ square
        torch.cuda.current_stream().wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            square @ square
        graph.replay()

    timed("CUDA graph capture", capture)
    print("| operation | cold (ms) | warm (ms) |")
    print("| --- | --- | --- |")
    for name, cold, warm in rows:
        print(f"| {name} | {cold:.1f} | {warm:.1f} |")


if __name__ == "__main__":
    main()
