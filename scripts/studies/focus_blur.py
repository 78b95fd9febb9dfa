"""Does a tilt series blur more where its views look through more depth (a focus that stays put
while the specimen tilts)?

In a view tilted by theta, a thin film's point seen at detector coordinate u (across the tilt
axis) lies u tan(theta) above or below the tilt axis's focus; a probe of convergence semi-angle
alpha blurs it by about alpha |u tan(theta)|.  This study renders a finished run's Gaussians
(atoms and non-atoms) into each view and finds, in five bands across the tilt axis, the extra
Gaussian blur (0-0.8 Å) that best matches the measured view after a per-band scale and plane.
A focus that stays put shows as blur growing with |u| in the tilted views and not in the flat
ones.

    python scripts/studies/focus_blur.py --data <series> --run <run directory>
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np

BLURS_A = np.round(np.arange(0.0, 0.81, 0.1), 2)
"""The extra blurs tried (Å): up to 0.8 Å, beyond an atom's own fitted width (about 0.55 Å)."""


def gaussians(run: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N, 3) positions, (N,) widths and (N,) amplitudes of a run's atoms and non-atoms."""
    with open(run / "atoms.csv") as f:
        rows = list(csv.DictReader(f))
    values = [[float(r[k]) for k in ("x_A", "y_A", "z_A", "sigma_A", "amplitude")] for r in rows]
    for line in (run / "non_atoms.xyz").read_text().splitlines()[2:]:
        values.append([float(v) for v in line.split()[1:6]])
    table = np.array(values).reshape(-1, 5)
    return table[:, :3], table[:, 3], table[:, 4]


def best_blurs(measured: np.ndarray, model: np.ndarray, bands: list[np.ndarray], pixel_A: float) -> list[float]:
    """For each band of rows, the blur of :data:`BLURS_A` whose blurred model, scaled and on a
    fitted plane, leaves the least squared residual."""
    from scipy.ndimage import gaussian_filter

    blurred = [gaussian_filter(model, b / pixel_A) if b > 0 else model for b in BLURS_A]
    best = []
    for band in bands:
        rows = slice(band[0], band[-1] + 1)
        target = measured[rows, 4:-4].ravel()
        costs = []
        for image in blurred:
            m = image[rows, 4:-4]
            r, c = np.meshgrid(np.arange(m.shape[0]), np.arange(m.shape[1]), indexing="ij")
            design = np.c_[m.ravel(), np.ones(m.size), r.ravel(), c.ravel()]
            coef, *_ = np.linalg.lstsq(design, target, rcond=None)
            costs.append(float(((design @ coef - target) ** 2).sum()))
        best.append(float(BLURS_A[int(np.argmin(costs))]))
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True, help="the tilt series the run fitted")
    parser.add_argument("--run", type=Path, required=True, help="the run directory (atoms.csv, non_atoms.xyz)")
    args = parser.parse_args()
    import torch

    from dataparsers.tilt_series_format import load_tilt_series
    from gaussian_atoms_method.physics.projector import project_gaussians

    series = load_tilt_series(args.data)
    if series.tilt_axis != "y":
        raise SystemExit(f"{args.data}: the study reads bands across a tilt axis along y (the columns)")
    means, sigmas, amplitudes = gaussians(args.run)
    n_views, height, width = series.projections.shape
    pixel = series.pixel_size_A
    rows_A = (np.arange(height) - series.centre_px[0]) * pixel
    cols_A = (np.arange(width) - series.centre_px[1]) * pixel
    model = project_gaussians(
        torch.tensor(means),
        torch.tensor(sigmas),
        torch.tensor(amplitudes),
        torch.tensor(series.detector_axes()),
        torch.tensor(rows_A),
        torch.tensor(cols_A),
    ).numpy()
    bands = np.array_split(np.arange(10, height - 10), 5)
    theta = np.asarray(series.angles_deg, dtype=np.float64)
    found = np.array(
        [best_blurs(series.projections[v].astype(np.float64), model[v], bands, pixel) for v in range(n_views)]
    )
    print("| views | " + " | ".join(f"u = {rows_A[b].mean():+.0f} Å" for b in bands) + " |")
    print("| --- |" + " --- |" * len(bands))
    for name, chosen in (("abs(theta) > 40 deg", np.abs(theta) > 40), ("abs(theta) < 20 deg", np.abs(theta) < 20)):
        print(f"| {name} ({chosen.sum()}) | " + " | ".join(f"{x:.2f}" for x in found[chosen].mean(0)) + " |")
    height_A = np.abs(rows_A[bands[0]].mean()) * np.tan(np.deg2rad(60))
    print(
        f"A focus fixed at the tilt axis would leave the outer bands of a 60-deg view {height_A:.0f} Å from it: "
        f"a probe of 20 mrad convergence semi-angle would blur them by about {0.02 * height_A:.1f} Å there."
    )


if __name__ == "__main__":
    main()
