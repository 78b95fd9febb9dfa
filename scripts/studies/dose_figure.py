"""The dose figure of issue 15: TPR, false positives per atom and RMSD against dose.

Top row: the aSi-208 benchmark (dose in e/Å²), ours beside the peer's own traced atoms, from
the ``results.csv`` that ``gaussian-atoms benchmark-peer`` writes (its ``peer_*`` columns).
Bottom row: the Au particle as Poisson counts (dose as the expected counts at the brightest
pixel), ours, FBP and SART, from the ``results.csv`` of
``gaussian-atoms benchmark-accuracy --particles au --noise-kind poisson``.

    python scripts/studies/dose_figure.py --peer outputs/benchmark-peer/results.csv \
        --au outputs/dose-au/results.csv --output docs/assets/dose.png
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

SCORES = (("tpr", "TPR"), ("fp_per_true_atom", "false positives per atom"), ("rmsd_pm", "RMSD (pm)"))


def read_rows(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def peer_series(rows: list[dict]) -> dict[str, tuple[list[float], dict[str, list[float]]]]:
    """{"ours" | "peer": (doses, {score: values})}, doses ascending."""
    rows = sorted(rows, key=lambda r: float(r["dose"]))
    doses = [float(r["dose"]) for r in rows]
    out = {"ours": (doses, {k: [float(r[k]) for r in rows] for k, _ in SCORES})}
    if all(r.get("peer_tpr") for r in rows):
        out["peer"] = (doses, {k: [float(r[f"peer_{k}"]) for r in rows] for k, _ in SCORES})
    return out


def method_series(rows: list[dict]) -> dict[str, tuple[list[float], dict[str, list[float]]]]:
    """{method: (doses, {score: values})} from a benchmark-accuracy CSV (dose = its noise column)."""
    out = {}
    for method in sorted({r["method"] for r in rows}):
        sel = sorted((r for r in rows if r["method"] == method), key=lambda r: float(r["noise_std"]))
        out[method] = ([float(r["noise_std"]) for r in sel], {k: [float(r[k]) for r in sel] for k, _ in SCORES})
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--peer", type=Path, required=True, help="results.csv of gaussian-atoms benchmark-peer")
    parser.add_argument("--au", type=Path, required=True, help="results.csv of benchmark-accuracy --noise-kind poisson")
    parser.add_argument("--output", type=Path, default=Path("docs/assets/dose.png"))
    args = parser.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [
        ("aSi-208", "dose (e/Å²)", peer_series(read_rows(args.peer))),
        ("Au, Poisson counts", "dose (counts at the brightest pixel)", method_series(read_rows(args.au))),
    ]
    from matplotlib.ticker import FuncFormatter, NullFormatter

    colours = {"ours": "C0", "peer": "C1", "fbp": "C2", "sart": "C3"}
    fig, axes = plt.subplots(2, 3, figsize=(12, 6.4))
    for row, (name, xlabel, series) in enumerate(rows):
        for label, (doses, values) in series.items():
            for col, (key, _) in enumerate(SCORES):
                axes[row, col].plot(doses, values[key], "o-", label=label, color=colours.get(label))
        ticks = sorted({d for doses, _ in series.values() for d in doses})
        for col, (_, title) in enumerate(SCORES):
            axes[row, col].set_xscale("log")
            axes[row, col].set_xticks(ticks)
            axes[row, col].xaxis.set_major_formatter(FuncFormatter(lambda x, _: f"{x:g}"))
            axes[row, col].xaxis.set_minor_formatter(NullFormatter())
            axes[row, col].set_title(f"{name}: {title}")
            axes[row, col].set_xlabel(xlabel)
        axes[row, 0].legend()
    fig.tight_layout()
    args.output.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.output, dpi=100)
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
