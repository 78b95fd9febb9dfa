"""Which part of the world's physics costs the fit its precision: one Ta sub-area's replica
(benchmark-film --replica) drawn with one piece of the physics at a time, each fitted with the
defaults and scored in benchmark-film's region.

Variants: ``full`` (film_benchmark.REPLICA: ADF atoms, aberrated probe with source and halo,
support, misregistration, gains), ``adf-atoms`` (ADF atoms through a 0.5 Å Gaussian probe, nothing
else), ``gaussian-atoms`` (Gaussian atoms through the full probe, nothing else), ``probe`` (ADF
atoms through the full probe, nothing else), and ``full`` less one piece: ``no-shifts``,
``no-support``, ``no-gains``.

    python scripts/studies/replica_physics.py --area 21 --variants adf-atoms no-shifts
"""

from __future__ import annotations

import argparse
from pathlib import Path

from gaussian_atoms_method.physics.microscope import ProbeOptics

VARIANTS = {
    "adf-atoms": {"probe": "gaussian", "blur_sigma_A": 0.5},
    "gaussian-atoms": {"potential": "gaussian", "optics": ProbeOptics(source_fwhm_A=0.7, halo_fraction=0.06)},
    "probe": {"optics": ProbeOptics(source_fwhm_A=0.7, halo_fraction=0.06)},
    "no-shifts": {
        "support_A": 30.0,
        "optics": ProbeOptics(source_fwhm_A=0.7, halo_fraction=0.06),
        "gain_scatter": 0.068,
    },
    "no-support": {
        "optics": ProbeOptics(source_fwhm_A=0.7, halo_fraction=0.06),
        "shift_px": 0.5,
        "gain_scatter": 0.068,
    },
    "no-gains": {"support_A": 30.0, "optics": ProbeOptics(source_fwhm_A=0.7, halo_fraction=0.06), "shift_px": 0.5},
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=Path("../shared/data/ta_film"))
    parser.add_argument("--area", type=int, default=21)
    parser.add_argument("--variants", nargs="+", default=["full", *VARIANTS])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--output", type=Path, default=Path("outputs/replica_physics"))
    args = parser.parse_args()

    from gaussian_atoms_method.harness import film_benchmark as fb

    full = dict(fb.REPLICA)
    for variant in args.variants:
        fb.REPLICA.clear()
        fb.REPLICA.update(full if variant == "full" else VARIANTS[variant])
        bench = fb.FilmBenchmark(
            args.data,
            args.output / variant,
            (args.area,),
            device=args.device,
            replica=True,
        )
        bench.run()
        print(f"{variant}: {(args.output / variant / 'results.md').read_text().strip().splitlines()[-1]}")
    fb.REPLICA.clear()
    fb.REPLICA.update(full)


if __name__ == "__main__":
    main()
