"""What a torch operation family's first use costs on a GPU, idle or behind queued work.

CUDA loads a kernel's module at its first use (lazy loading).  In a fresh process, with torch and
the device ready, each family below is called on a few elements: ``--queued-ms 0`` times its
cold and warm calls on an idle GPU; ``--queued-ms N`` first queues about N ms of warm GPU work
(in-place additions on 200 MB) and times the host's return from the cold call, which shows
whether the first use waits for that queue.  Families loaded by an earlier row read about
0.1 ms.  Behind :mod:`gaussian_atoms_method.launch.kernel_warmup`.

    python scripts/studies/kernel_first_use.py --queued-ms 0
    python scripts/studies/kernel_first_use.py --queued-ms 50
"""

from __future__ import annotations

import argparse
import sys
import time


def families(torch, dev):
    """name -> a call of that family on a few elements."""
    f = torch.tensor([3.0, 1.0, 2.0, 5.0], device=dev)
    i = torch.tensor([0, 1, 1, 0], device=dev)
    m = torch.tensor([True, False, True, False], device=dev)
    return {
        "sort": lambda: torch.sort(f),
        "where": lambda: torch.where(m, f, f),
        "pow": lambda: f.pow(2),
        "remainder": lambda: torch.remainder(f, 2.0),
        "floor": lambda: torch.floor(f),
        "floor_divide": lambda: torch.div(f, 2.0, rounding_mode="floor"),
        "bitwise_not": lambda: ~m,
        "neg": lambda: f.neg(),
        "linalg.vector_norm": lambda: torch.linalg.vector_norm(f),
        "index_add_": lambda: torch.zeros(2, device=dev).index_add_(0, i, f),
        "gather": lambda: torch.gather(f, 0, i),
        "repeat_interleave": lambda: torch.repeat_interleave(i + 1),
        "mean": lambda: f.mean(),
        "max": lambda: f.max(),
        "nonzero": lambda: m.nonzero(),
        "eq": lambda: f == 1.0,
        "div": lambda: f / 3.0,
        "mul": lambda: f * 3.0,
        "log": lambda: f.log(),
        "abs": lambda: f.abs(),
        "unique": lambda: torch.unique(i),
        "index": lambda: f[i],
        "cat": lambda: torch.cat([f, f]),
        "cuBLAS (matmul)": lambda: f[None] @ f[:, None],
        "cuSOLVER (solve)": lambda: torch.linalg.solve(torch.eye(2, device=dev) * 2, f[:2, None]),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--queued-ms", type=float, default=0.0, help="GPU work queued before each cold call (ms)")
    args = parser.parse_args()
    import torch

    if not torch.cuda.is_available():
        sys.exit("kernel_first_use.py: torch sees no CUDA device here; run it on a GPU machine")
    dev = "cuda"
    torch.zeros(1, device=dev).sum().item()
    big = torch.zeros(50_000_000, device=dev)
    big.add_(1.0)
    torch.cuda.synchronize()
    start = time.perf_counter()
    for _ in range(100):
        big.add_(1.0)
    torch.cuda.synchronize()
    add_ms = (time.perf_counter() - start) * 10.0
    calls = families(torch, dev)
    torch.cuda.synchronize()
    if args.queued_ms > 0:
        print(f"| family | the cold call's return, {args.queued_ms:.0f} ms queued (ms) | the GPU's end (ms) |")
    else:
        print("| family | cold (ms) | warm (ms) |")
    print("| --- | --- | --- |")
    total = 0.0
    for name, call in calls.items():
        if args.queued_ms > 0:
            for _ in range(int(args.queued_ms / add_ms)):
                big.add_(1.0)
        start = time.perf_counter()
        call()
        first = (time.perf_counter() - start) * 1e3
        torch.cuda.synchronize()
        second = (time.perf_counter() - start) * 1e3
        if args.queued_ms <= 0:
            first = second
            start = time.perf_counter()
            call()
            torch.cuda.synchronize()
            second = (time.perf_counter() - start) * 1e3
        total += first
        print(f"| {name} | {first:.1f} | {second:.2f} |")
    print(f"all cold calls: {total:.0f} ms")


if __name__ == "__main__":
    main()
