"""Tools a user runs on finished runs and on their inputs: ``held-out-views``,
``check-precision``, ``input-matrix``, ``screenshot``."""

from __future__ import annotations

import shlex
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional


@dataclass
class HeldOutViews:
    """Choose the point-spread function by the views a fit did not see: for each candidate
    kernel, fit the even views and predict the odd ones, then the other way round; the kernel
    whose fits predict the unseen views best is the one the data support (held_out.md)."""

    data: Path
    """A tilt-series directory (tilt_series.json)."""
    output: Path = Path("outputs/held-out")
    kernels: tuple[str, ...] = ("learned", "0,0.1,0.1", "0,0.15,0.2", "0,0.2,0.3")
    """``learned`` (the default run) or three intensity fractions ``a,b,c`` at 1, 2 and 4 Å, held."""
    device: Literal["cpu", "cuda"] = "cpu"
    iterations: int = 3000
    interior_px: tuple[int, int] = (0, 0)
    """Rows and columns left out at each detector edge when scoring."""
    train_args: str = ""
    """Further ns-train options, given with "=", e.g. --train-args="--pipeline.model.background plane"."""
    alignment: bool = False
    """Instead of kernels: per-view shifts (--pipeline.model.refine-alignment) and gains
    (--pipeline.model.refine-gain) off and on, each held-out view scored after its own best shift
    and gain; the run to keep is the one the views prefer."""

    def main(self) -> None:
        from gaussian_atoms_method.harness.kernel_choice import (
            ALIGNMENT_CANDIDATES,
            compare_kernels,
            compare_settings,
        )

        if self.alignment:
            extra = tuple(shlex.split(self.train_args))
            candidates = {name: (args + extra, kernel) for name, (args, kernel) in ALIGNMENT_CANDIDATES.items()}
            compare_settings(self.data, self.output, candidates, self.device, self.iterations, self.interior_px, True)
            return
        compare_kernels(self.data, self.output, self.kernels, self.device, self.iterations, self.interior_px,
                        tuple(shlex.split(self.train_args)))  # fmt: skip


@dataclass
class CheckPrecision:
    """Each atom's stated position precision against its actual error, on finished runs whose
    data have a truth file: per axis, the median stated standard deviation, the actual RMS error
    and the share within one and two of them (0.683 and 0.954 if the statement were exact)."""

    load_config: tuple[Path, ...]
    """The runs' config.yml files."""
    output: Optional[Path] = None
    """Also write the tables here (markdown)."""

    def main(self) -> None:
        from gaussian_atoms_method.harness.precision_check import check_precision, precision_table

        for config in self.load_config:
            if not config.is_file():
                raise FileNotFoundError(f"{config}: run config not found")
        table = precision_table([check_precision(c) for c in self.load_config])
        print(table)
        if self.output is not None:
            self.output.write_text(table)


@dataclass
class InternalFloor:
    """Fit a tilt series, then read the error its stated precision cannot show on an internal
    replica of its own atoms (drawn again through ADF physics in the series' geometry, level and
    noise, with the offsets and gains the fit read off its views, and fitted again): prints the
    floor and the command that states each atom's precision with it."""

    data: Path
    """The tilt series (a tilt_series.json directory or a file the readers take)."""
    species: str
    """The specimen's element, e.g. Ta (the replica draws each atom as it)."""
    support_A: float = 0.0
    """The carbon support film under the specimen, Å thick (0: none): a bias alike in every view
    that the stated precision does not hold, so the replica must carry it."""
    extended_object: Literal["auto", "on", "off"] = "auto"
    """As --pipeline.model.extended-object: "on" for a film wider than the detector."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    seed: int = 0
    """The replica's draws."""

    def main(self) -> None:
        import numpy as np

        import gaussian_atoms_method as ga
        from dataparsers.tilt_series_format import load_tilt_series
        from gaussian_atoms_method.harness.internal_floor import internal_floor

        series = load_tilt_series(self.data)
        options = {"extended_object": self.extended_object}
        atoms = ga.reconstruct(series, species=self.species, device=self.device, progress=False, **options)
        floor = internal_floor(
            series, atoms, species=self.species, seed=self.seed, support_A=self.support_A, device=self.device, **options
        )
        values = " ".join(f"{f:.3f}" for f in np.round(floor.floor_A, 3))
        held = "/".join(f"{c:.2f}" for c in floor.coverage_95)
        shifts = " / ".join(f"{s:.2f}" for s in floor.shifts_rms_px)
        print(
            f"internal floor: on a replica of the fit's {len(atoms)} atoms ({floor.found:.3f} found, RMSD "
            f"{floor.rmsd_pm:.1f} pm, misregistration {shifts} px RMS) the stated 95% intervals held x/y/z {held}; "
            f"the error they missed: {values} Å. State it with\n"
            f"  gaussian-atoms train --pipeline.model.extended-object {self.extended_object} "
            f"--pipeline.model.precision-floor-A {values} tilt-series --data {self.data} --species {self.species}"
        )


@dataclass
class InputMatrix:
    """Run every broken and odd tilt series of the catalogue through the front door and print a
    table: a broken one passes with one line of its own, a non-zero exit, no traceback and no
    run directory left; an odd one passes when it trains.  Exit status 1 if any fails."""

    launcher: Literal["ns-train", "gaussian-atoms"] = "ns-train"
    output: Path = Path("outputs/input-matrix")

    def main(self) -> None:
        from gaussian_atoms_method.harness.input_matrix import run_matrix

        rows = run_matrix(self.launcher, self.output)
        failed = [r["case"] for r in rows if not r["passed"]]
        print(f"{len(rows) - len(failed)} passed, {len(failed)} failed" + (f": {failed}" if failed else ""))
        if failed:
            raise SystemExit(1)


@dataclass
class Screenshot:
    """A PNG of nerfstudio's viewer showing a finished run's atoms, taken in headless Chromium
    (Selenium; WebGL through SwiftShader, no GPU).  Exit status 1 unless the atoms show.  Needs
    ``apt-get install chromium chromium-driver`` and ``pip install selenium``."""

    load_config: Path
    """The run's config.yml."""
    output: Path = Path("viewer.png")
    wait_s: float = 25.0
    """Seconds the page is given to connect and draw the scene."""

    def main(self) -> None:
        from gaussian_atoms_method.harness.viewer_screenshot import screenshot

        if not self.load_config.is_file():
            raise FileNotFoundError(f"{self.load_config}: run config not found")
        try:
            fraction = screenshot(self.load_config, self.output, self.wait_s)
        except (RuntimeError, TimeoutError, ImportError) as exc:
            raise ValueError(str(exc)) from None
        print(f"wrote {self.output}: {fraction:.4f} of the pixels are atom-coloured")
        if fraction < 1e-3:
            print("gaussian-atoms screenshot: the atoms are not visible in the screenshot", file=sys.stderr)
            raise SystemExit(1)
