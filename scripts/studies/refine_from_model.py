"""Is the authors' Ta model a resting place of the plain likelihood, and is ours?

Takes a finished ``gaussian-atoms benchmark-film`` sub-area and refines one set of Gaussians
against its views by least squares alone (one constant per view, no kernel, no density control,
no hard core): the run's own Gaussians (``--start ours``), or the run's with its atoms inside the
scored region replaced by the model's atoms (``--start model``, each with our atoms' median width
and height).  Every ``--every`` steps it prints the residual's sum of squares and the atoms'
scores against the model (found within 0.75 Å, extra per model atom, RMSD).  Where the model is
where the data put the atoms, its atoms stay within 0.75 Å of where they started.

``--tied``: every atom has one mass and one width (one element, one atom); the non-atoms keep
their own.  ``--grid-sigma-A S``: a non-atomic density of Gaussians of width S on a grid 2S apart
over the atoms' box, each with its own non-negative height, for misfit that is not atoms.

    python scripts/studies/refine_from_model.py --output outputs/benchmark-film --area 23 --start model
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--output", type=Path, required=True, help="a benchmark-film --output folder")
    parser.add_argument("--area", type=int, required=True)
    parser.add_argument("--film", type=Path, default=Path("../shared/data/ta_film"), help="the film's folder")
    parser.add_argument("--start", choices=("ours", "model"), default="model")
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--every", type=int, default=300, help="print the scores every this many steps")
    parser.add_argument("--tied", action="store_true", help="one mass and one width for every atom")
    parser.add_argument("--grid-sigma-A", type=float, default=0.0, help="a non-atomic density's width (0: none)")
    parser.add_argument("--lr-A", type=float, default=0.005, help="Adam's step on the positions, Å")
    args = parser.parse_args()
    try:
        report(args)
    except (OSError, ValueError, KeyError) as err:  # a missing run or file, a series that cannot be read
        raise SystemExit(f"refine_from_model.py: {err}") from None


def report(args) -> None:
    """Refine and print the study's table for the parsed command line."""
    import torch

    from dataparsers.tilt_series_format import load_tilt_series
    from gaussian_atoms_method.atoms.atom_set import read_atoms
    from gaussian_atoms_method.atoms.view_prediction import run_gaussians
    from gaussian_atoms_method.harness import film_benchmark as fb
    from gaussian_atoms_method.physics.geometry import pixel_centres
    from gaussian_atoms_method.physics.projector import project_gaussians

    data = args.output / "data" / f"area{args.area}"
    run = args.output / "runs" / f"area{args.area}" / "ours" / "gaussian-atoms" / "run"
    series = load_tilt_series(data)  # a missing sub-area: one line (a ValueError), before the work
    every, ours = run_gaussians(run), read_atoms(run / "atoms.xyz")
    model = fb.model_in_area_A(args.film, args.area)
    box, inside = fb.scored_region(model, series.projections.shape[1:], tuple(series.centre_px))
    pos, sig, amp = (np.array(v, dtype=np.float64) for v in (every.positions, every.sigmas, every.amplitudes))
    is_atom = np.arange(len(pos)) < len(ours)  # run_gaussians lists atoms.xyz first
    if args.start == "model":
        _, shift, _, _ = fb.matched_to_model(ours.positions, model, inside)
        replaced = is_atom & np.all((pos + shift >= box[0]) & (pos + shift <= box[1]), axis=1)
        start = model[inside] - shift
        pos = np.concatenate([pos[~replaced], start])
        sig = np.concatenate([sig[~replaced], np.full(len(start), np.median(sig[is_atom]))])
        amp = np.concatenate([amp[~replaced], np.full(len(start), np.median(amp[is_atom]))])
        is_atom = np.concatenate([is_atom[~replaced], np.ones(len(start), dtype=bool)])
    mass = amp * (2 * np.pi * sig**2) ** 1.5

    dt = torch.float32
    origin = np.asarray(series.origin_A, dtype=np.float64)
    means = torch.tensor(pos - origin, dtype=dt, requires_grad=True)
    log_sig = torch.tensor(np.log(sig), dtype=dt, requires_grad=True)
    log_amp = torch.tensor(np.log(amp), dtype=dt, requires_grad=True)
    atom = torch.as_tensor(is_atom)
    one_log_sig = torch.tensor(float(np.median(np.log(sig[is_atom]))), requires_grad=True)
    one_log_mass = torch.tensor(float(np.median(np.log(mass[is_atom]))), requires_grad=True)
    h, w = series.projections.shape[1:]
    rows = torch.as_tensor(pixel_centres(h, series.pixel_size_A, series.centre_px[0]), dtype=dt)
    cols = torch.as_tensor(pixel_centres(w, series.pixel_size_A, series.centre_px[1]), dtype=dt)
    axes = torch.as_tensor(series.detector_axes(), dtype=dt)
    measured = torch.as_tensor(np.asarray(series.projections), dtype=dt)
    groups = [
        {"params": [means], "lr": args.lr_A},
        {"params": [log_sig, log_amp, one_log_sig, one_log_mass], "lr": 0.005},
    ]
    grid = None
    if args.grid_sigma_A > 0:
        lo, hi = ours.positions.min(axis=0), ours.positions.max(axis=0)
        axes_A = [np.arange(lo[i], hi[i] + 2 * args.grid_sigma_A, 2 * args.grid_sigma_A) for i in range(3)]
        grid = torch.tensor(np.stack(np.meshgrid(*axes_A, indexing="ij"), -1).reshape(-1, 3) - origin, dtype=dt)
        grid_log_amp = torch.full((len(grid),), -8.0, requires_grad=True)  # starts empty
        grid_sig = torch.full((len(grid),), args.grid_sigma_A)
        groups.append({"params": [grid_log_amp], "lr": 0.05})
    optimiser = torch.optim.Adam(groups)

    def widths_heights():
        if not args.tied:
            return log_sig.exp(), log_amp.exp()
        s = torch.where(atom, one_log_sig.exp(), log_sig.exp())
        tied_height = one_log_mass.exp() / (2 * np.pi * s**2) ** 1.5
        return s, torch.where(atom, tied_height, log_amp.exp())

    print(
        f"sub-area {args.area}, start {args.start}{', tied' if args.tied else ''}"
        f"{f', non-atomic density {args.grid_sigma_A} Å ({len(grid)} Gaussians)' if grid is not None else ''}"
    )
    print("| step | residual sum of squares | found | extra per model atom | RMSD (pm) | atoms in the region | s |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    began = time.time()
    for step in range(args.steps + 1):
        optimiser.zero_grad()
        s, a = widths_heights()
        image = project_gaussians(means, s, a, axes, rows, cols)
        if grid is not None:
            image = image + project_gaussians(grid, grid_sig, grid_log_amp.exp(), axes, rows, cols)
        residual = measured - image
        residual = residual - residual.mean(dim=(1, 2), keepdim=True)
        loss = (residual**2).sum()
        if step % args.every == 0 or step == args.steps:
            placed = means.detach().double().numpy()[is_atom] + origin
            sc = fb.score_in_region(placed, model, box, inside)
            print(
                f"| {step} | {float(loss.detach()):.4e} | {sc['found']:.3f} | {sc['extra_per_model_atom']:.3f} | "
                f"{sc['rmsd_pm']:.1f} | {sc['n_pred']} | {time.time() - began:.0f} |",
                flush=True,
            )
        if step == args.steps:
            break
        loss.backward()
        optimiser.step()


if __name__ == "__main__":
    main()
