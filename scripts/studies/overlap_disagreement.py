"""Which atoms overlapping sub-areas disagree on: the share of a strip's reports in the common
interiors that the other fit reports too (a report within half the hard core of it; the common
interior as ``film/stitch.pair_agreement`` takes it, which also asks that report to have it as its
nearest), by the atoms' evidence (trusted, proven, open in
depth, significance) and by their depth in the film; and where a disagreeing report's
counterpart is: a Gaussian the other fit calls a non-atom, or the other fit's nearest Gaussian
of any kind and how far (``non_atoms.xyz`` beside ``atoms.csv``).

    gaussian-atoms benchmark-film --strips 1 --no-registration-by-overlap --output runs/strips
    python scripts/studies/overlap_disagreement.py --run runs/strips/strip1 --strip 1
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", type=Path, required=True, help="a strip's folder (benchmark-film --strips)")
    parser.add_argument("--strip", type=int, required=True, choices=(1, 2))
    parser.add_argument("--film", type=Path, default=Path("../shared/data/ta_film"), help="the film's folder")
    args = parser.parse_args()
    reports = common_reports(args.run, args.strip, args.film)
    agree = reports["agree"]
    print(f"| atoms | reports | agree |\n| --- | --- | --- |\n| all | {len(agree):,} | {agree.mean():.3f} |")
    for name in ("trusted", "proven", "depth_open"):
        for value in (True, False):
            sel = reports[name] == value
            print(f"| {name} {value} | {sel.sum():,} | {agree[sel].mean():.3f} |")
    for lo, hi in ((0, 5), (5, 10), (10, 20), (20, np.inf)):
        sel = (reports["significance"] >= lo) & (reports["significance"] < hi)
        if sel.any():
            print(f"| significance {lo}-{hi} | {sel.sum():,} | {agree[sel].mean():.3f} |")
    z = reports["z_A"]
    edges = np.quantile(z, [0, 0.1, 0.25, 0.5, 0.75, 0.9, 1])
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (z >= lo) & (z <= hi)
        print(f"| depth {lo:.1f} to {hi:.1f} Å | {sel.sum():,} | {agree[sel].mean():.3f} |")
    nearest, non_atom = reports["nearest_A"], reports["non_atom"]
    print(
        f"the {(~agree).sum():,} disagreeing: the other fit holds a non-atom there {np.mean(non_atom[~agree]):.3f}; "
        "its nearest Gaussian of any kind "
        + ", ".join(
            f"{lo}-{hi} Å {np.mean((nearest[~agree & ~non_atom] >= lo) & (nearest[~agree & ~non_atom] < hi)):.3f}"
            for lo, hi in ((0, 1.6), (1.6, 2.2), (2.2, np.inf))
        )
        + " (of those not a non-atom there); along the beam: median |dz| / distance "
        + f"{np.median(reports['dz_share'][~agree & ~non_atom]):.2f}"
    )
    at_core, lighter = reports["non_atom_at_core"][non_atom], reports["non_atom_log_mass"][non_atom]
    print(
        f"those non-atoms: within the hard core of an atom the other fit reports {np.mean(at_core):.2f}; "
        "else lighter than its atoms' median by more than a quarter "
        f"{np.mean(~at_core & (lighter < np.log(0.75))):.2f}; "
        f"median log mass against that median {np.median(lighter):.2f}"
    )
    sig, std = reports["significance"], reports["std_A"]
    print(
        f"median significance {np.median(sig[~agree]):.1f} disagreeing, {np.median(sig[agree]):.1f} agreeing; "
        f"median stated precision (norm) {np.median(std[~agree]):.2f} and {np.median(std[agree]):.2f} Å"
    )


def common_reports(run: Path, strip: int, film: Path) -> dict[str, np.ndarray]:
    """Per report of an atom in a common interior (every overlapping pair, both ways): whether
    the other fit reports it (``agree``), and the atom's evidence and depth (``z_A``)."""
    from gaussian_atoms_method.atoms.atom_set import read_atoms
    from gaussian_atoms_method.atoms.hard_core import hard_core_from_species
    from gaussian_atoms_method.film.stitch import Reports, common_interior
    from gaussian_atoms_method.film.subareas import published_subareas
    from gaussian_atoms_method.harness.film_strip import FULL_VOLUME_CENTRE_VOX, PIXEL_SIZE_A, STRIPS

    subareas = published_subareas(film, list(STRIPS[strip]), run / "data", PIXEL_SIZE_A, tuple(FULL_VOLUME_CENTRE_VOX))
    half = hard_core_from_species("Ta") / 2
    atoms = {s.name: read_atoms(run / "runs" / s.name / "gaussian-atoms" / "run" / "atoms.csv") for s in subareas}
    non_atoms = {
        s.name: read_atoms(run / "runs" / s.name / "gaussian-atoms" / "run" / "non_atoms.xyz") for s in subareas
    }
    offsets = {s.name: np.asarray(s.offset_A) for s in subareas}
    reports = {
        s.name: Reports(s.name, atoms[s.name].positions + np.asarray(s.offset_A), s.interior_A) for s in subareas
    }
    keys = ("agree", "trusted", "proven", "depth_open", "significance", "z_A", "std_A")
    keys += ("non_atom", "nearest_A", "dz_share", "non_atom_at_core", "non_atom_log_mass")
    out: dict[str, list] = {k: [] for k in keys}
    for i, a in enumerate(subareas):
        for b in subareas[i + 1 :]:
            common = common_interior(reports[a.name], reports[b.name], half)
            if common is None:
                continue
            for mine, theirs in ((a.name, b.name), (b.name, a.name)):
                here, there = reports[mine], reports[theirs]
                which = np.flatnonzero(common.inside(here.positions) & here.inside(here.positions))
                other = there.positions[there.inside(there.positions)]
                if len(which) == 0 or len(other) == 0:
                    continue
                distance, _ = cKDTree(other).query(here.positions[which], distance_upper_bound=half)
                rest = non_atoms[theirs].positions + offsets[theirs]
                to_non, non = (
                    cKDTree(rest).query(here.positions[which]) if len(rest) else (np.full(len(which), np.inf), None)
                )
                near_non = to_non < half
                core = 2 * half
                at_core = np.zeros(len(which), bool)
                log_mass = np.full(len(which), np.nan)
                if non is not None:
                    at_core = cKDTree(there.positions).query(rest[non])[0] < core
                    log_mass = np.log(non_atoms[theirs].masses[non]) - np.median(np.log(atoms[theirs].masses))
                out["non_atom_at_core"].append(at_core)
                out["non_atom_log_mass"].append(log_mass)
                everything = np.r_[there.positions, rest]
                nearest, index = cKDTree(everything).query(here.positions[which])
                out["non_atom"].append(near_non & ~(distance < half))
                out["nearest_A"].append(nearest)
                dz = np.abs(everything[index, 2] - here.positions[which, 2])
                out["dz_share"].append(dz / np.maximum(nearest, 1e-9))
                fit = atoms[mine]
                out["agree"].append(distance < half)
                out["trusted"].append(np.ones(len(which), bool) if fit.trusted is None else fit.trusted[which] > 0)
                out["proven"].append(np.asarray(fit.proven, bool)[which])
                out["depth_open"].append(np.asarray(fit.depth_open, bool)[which])
                out["significance"].append(np.asarray(fit.significance, float)[which])
                out["z_A"].append(fit.positions[which, 2])
                out["std_A"].append(np.linalg.norm(fit.position_std_A[which], axis=1))
    return {k: np.concatenate(v) for k, v in out.items()}


if __name__ == "__main__":
    main()
