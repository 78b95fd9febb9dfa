"""Choose the point-spread function by the views a fit did not see (two-fold cross-validation).

For each candidate kernel, ``ns-train gaussian-atoms`` fits the even views and predicts the odd
ones, then the other way round (:mod:`gaussian_atoms_method.harness.held_out`); the kernel whose
fits predict the unseen views best is the one the data support.  ``learned`` is the default
run; ``a,b,c`` holds a kernel with those intensity fractions at 1, 2 and 4 Å
(``--pipeline.model.psf fixed --pipeline.model.psf-weights a b c``).  Writes held_out.csv and
held_out.md; the chosen kernel goes to every run on data from the same microscope.

    gaussian-atoms held-out-views --data data/film --output outputs/held-out \\
        --kernels learned 0,0.1,0.1 0,0.15,0.2 0,0.2,0.3 [--device cuda] [--interior-px 8 4]
"""

from __future__ import annotations

import csv
import re
from pathlib import Path


def kernel_args(kernel: str) -> tuple[str, ...]:
    """ns-train options for a candidate: ``learned`` or ``a,b,c``."""
    if kernel == "learned":
        return ()
    return ("--pipeline.model.psf", "fixed", "--pipeline.model.psf-weights", *kernel.split(","))


def kernel_of_run(run_dir: Path, kernel: str) -> list[float]:
    """The kernel a run ended with: the fractions it wrote (learned; ``psf.json``,
    :func:`~gaussian_atoms_method.atoms.view_prediction.run_kernel`), or the ones it held."""
    from gaussian_atoms_method.atoms.view_prediction import run_kernel

    if kernel != "learned":
        return [float(v) for v in kernel.split(",")]
    return run_kernel(run_dir) or [0.0, 0.0, 0.0]


class KernelChoiceError(ValueError):
    """A candidate kernel or the tilt series that cannot be compared; the message names it."""


def compare_kernels(
    data: Path,
    output: Path,
    kernels: tuple[str, ...] = ("learned", "0,0.1,0.1", "0,0.15,0.2", "0,0.2,0.3"),
    device: str = "cpu",
    iterations: int = 3000,
    interior_px: tuple[int, int] = (0, 0),
    train_args: tuple[str, ...] = (),
) -> list[dict]:
    """For each candidate kernel: fit the even views, predict the odd ones, and the other way
    round; rows with the held-out RMS residual each way and their mean.  Writes held_out.csv
    and held_out.md in ``output``."""
    for kernel in kernels:
        if kernel != "learned" and not re.fullmatch(r"[\d.]+,[\d.]+,[\d.]+", kernel):
            raise KernelChoiceError(f"--kernels takes 'learned' or three fractions 'a,b,c', got {kernel!r}")
    candidates = {kernel: (kernel_args(kernel) + tuple(train_args), kernel) for kernel in kernels}
    return compare_settings(data, output, candidates, device, iterations, interior_px)


ALIGNMENT_CANDIDATES = {
    "registration off": ((), "learned"),
    "shifts": (("--pipeline.model.refine-alignment", "True"), "learned"),
    "gains": (("--pipeline.model.refine-gain", "True"), "learned"),
    "shifts and gains": (
        ("--pipeline.model.refine-alignment", "True", "--pipeline.model.refine-gain", "True"),
        "learned",
    ),
}
"""``held-out-views --alignment``: per-view shifts and gains learned or not, judged by the views
held out, each held-out view scored after its own best shift and gain (its misregistration and
dose are no fit's)."""


def compare_settings(
    data: Path,
    output: Path,
    candidates: dict,
    device: str = "cpu",
    iterations: int = 3000,
    interior_px: tuple[int, int] = (0, 0),
    fit_registration: bool = False,
) -> list[dict]:
    """For each candidate (name -> (ns-train options, its kernel: ``learned`` or ``a,b,c``)):
    fit the even views, predict the odd ones, and the other way round (with ``fit_registration``,
    each held-out view after its own best in-plane shift and gain); rows with the held-out RMS
    residual each way and their mean.  Writes held_out.csv and held_out.md in ``output``."""
    from dataparsers.tilt_series_format import load_tilt_series
    from gaussian_atoms_method.atoms.view_prediction import held_out_rms, run_gaussians
    from gaussian_atoms_method.harness.benchmark import train_ours
    from gaussian_atoms_method.harness.held_out import split_views

    try:
        series = load_tilt_series(data)
    except (OSError, ValueError) as err:
        raise KernelChoiceError(str(err)) from None
    folds = dict(zip(("even", "odd"), split_views(series, output / "views")))
    rows = []
    for name, (args, kernel) in candidates.items():
        row = {"kernel": name}
        for fit, held in (("even", "odd"), ("odd", "even")):
            run_dir = output / "runs" / re.sub(r"[^\w.-]+", "_", name) / fit
            train_ours(folds[fit], run_dir, iterations, device, tuple(args))
            fitted = run_dir / "ours" / "gaussian-atoms" / "run"
            held_views, kernel_weights = load_tilt_series(folds[held]), kernel_of_run(fitted, kernel)
            row[f"{fit}->{held}"] = held_out_rms(
                run_gaussians(fitted), held_views, kernel_weights, tuple(interior_px), fit_registration
            )
            row[f"kernel {fit}"] = kernel_weights
        row["mean"] = 0.5 * (row["even->odd"] + row["odd->even"])
        rows.append(row)
        print(
            f"{name}: held-out rms {row['even->odd']:.4g} (even -> odd), {row['odd->even']:.4g} (odd -> even)",
            flush=True,
        )
    write_kernel_table(rows, output)
    return rows


def write_kernel_table(rows: list[dict], output: Path) -> None:
    """held_out.csv and held_out.md: each kernel's held-out RMS both ways, and the one preferred."""
    best = min(rows, key=lambda r: r["mean"])
    fields = ["kernel", "even->odd", "odd->even", "mean"]
    with open(output / "held_out.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    lines = [
        "| candidate | held-out rms, even -> odd | odd -> even | mean |",
        "| --- | --- | --- | --- |",
    ]
    lines += [f"| {r['kernel']} | {r['even->odd']:.5g} | {r['odd->even']:.5g} | {r['mean']:.5g} |" for r in rows]
    (output / "held_out.md").write_text("\n".join(lines) + f"\n\nThe views held out prefer: {best['kernel']}\n")
    print(f"the views held out prefer {best['kernel']}; wrote {output / 'held_out.md'}")
