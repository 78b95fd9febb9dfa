"""``gaussian-atoms film``: a film wider than the field, fitted in overlapping sub-areas on Ray
and joined (:mod:`gaussian_atoms_method.film`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional

OPTIONS = {"device": "--device", "max_steps": "--max-num-iterations", "tasks_per_gpu": "--tasks-per-gpu"}
"""The options :func:`gaussian_atoms_method.film.film.check_settings` names, as this verb spells them."""


@dataclass
class Film:
    """Fit a film in overlapping sub-areas as Ray tasks and join them into one set of atoms.

    Input: sub-area stacks as sub-area AET publishes them (``--published DIR --areas 1-16
    --pixel-size-A 0.3216 --full-centre-vox 201 176 171``), or one aligned tilt series cut
    into tiles (``--series DIR``; ``--tile-px 131 61 --step-px 18 61`` to choose them)."""

    output: Path
    """Where the sub-areas' series, their fits (``runs/``) and the film's files go; a second run
    into it resumes (finished sub-areas are read back)."""
    published: Optional[Path] = None
    """A folder of ``Projections_area<N>.mat``, ``angles.mat`` and ``alignPara.mat``."""
    areas: str = ""
    """The published sub-areas to use: ``1-16``, ``8,21,23`` or a mix."""
    pixel_size_A: Optional[float] = None
    """The published stacks' pixel size, Å (the .mat files do not hold it)."""
    full_centre_vox: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """The film frame's origin, 1-based voxels of the published full volume (``CropCen``'s frame)."""
    euler_convention: Literal["zyz", "zyx"] = "zyx"
    """Axes of the published Euler angles: zyx as RESIRE (sub-area AET) writes them, zyz as GENFIRE."""
    series: Optional[Path] = None
    """One aligned tilt series (a directory with tilt_series.json, or a file) to cut into tiles."""
    tile_px: tuple[int, int] = (0, 0)
    """A tile's size (rows across the tilt axis, columns along it), pixels; 0 0: twice the film's
    thickness read from the series across, the whole field along (:func:`default_tiling`)."""
    step_px: tuple[int, int] = (0, 0)
    """Between tiles, pixels; 0 0: each point in about 7 tiles."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    """Where each sub-area trains: cuda (one GPU a task), cpu (two or more cores a task), auto
    (the GPUs where torch sees them)."""
    address: Optional[str] = None
    """A Ray cluster's address (default: a local cluster on this machine)."""
    species: Optional[str] = None
    """The film's elements, e.g. Ta: they set the hard core of every sub-area's fit and of the join
    of their reports."""
    max_num_iterations: int = 3000
    tasks_per_gpu: int = 1
    """Sub-areas fitted at once on each GPU: a sub-area's fit holds a small part of its memory
    and spends most of its time on kernel launches, so several can share one."""
    registration_by_overlap: bool = True
    """Fit every sub-area twice, without and with per-view shifts and gains, and keep the set whose
    overlapping fits place the atoms they share closer together, agreeing on no fewer atoms
    (``registration.json``): what a lone series cannot decide, at twice the fits' time
    (``--no-registration-by-overlap``: one fit each, without)."""

    def subareas(self):
        """The sub-areas the options name (written as tilt series under ``output/data``)."""
        from gaussian_atoms_method.film.subareas import published_subareas, tile_series

        if (self.published is None) == (self.series is None):
            raise ValueError("give either --published DIR (with --areas) or --series DIR (with --tile-px, --step-px)")
        data = self.output / "data"
        if self.published is not None:
            if self.pixel_size_A is None:
                raise ValueError("--pixel-size-A: the published stacks' pixel size is needed (Å)")
            return published_subareas(
                self.published,
                parse_areas(self.areas),
                data,
                self.pixel_size_A,
                self.full_centre_vox,
                self.euler_convention,
            )
        from dataparsers.tilt_series_format import load_tilt_series
        from gaussian_atoms_method.film.subareas import default_tiling

        if min(self.tile_px) < 0 or min(self.step_px) < 0:
            raise ValueError("--tile-px and --step-px: pixels, positive (0 0: chosen from the film's thickness)")
        series = load_tilt_series(self.series)
        tile, step = default_tiling(series)
        tile = tuple(t if given == 0 else given for t, given in zip(tile, self.tile_px))
        step = tuple(t if given == 0 else given for t, given in zip(step, self.step_px))
        return tile_series(series, tile, step, data)

    def main(self) -> None:
        from gaussian_atoms_method.film.film import check_settings, reconstruct_film

        # the library's own checks, by the options' names, before the sub-areas are written
        check_settings(
            self.device, self.species, self.max_num_iterations, self.address, self.tasks_per_gpu, {}, OPTIONS
        )
        reconstruct_film(
            self.subareas(),
            self.output,
            self.device,
            self.species,
            self.max_num_iterations,
            self.address,
            tasks_per_gpu=self.tasks_per_gpu,
            registration_by_overlap=self.registration_by_overlap,
        )


def parse_areas(text: str) -> list[int]:
    """``"1-3,8"`` -> ``[1, 2, 3, 8]`` (each once); a ``ValueError`` naming ``--areas`` otherwise."""
    out: list[int] = []
    try:
        for part in filter(None, (p.strip() for p in text.split(","))):
            lo, _, hi = part.partition("-")
            out += list(range(int(lo), int(hi or lo) + 1))
    except ValueError:
        raise ValueError(f"--areas {text!r}: expected numbers and ranges, e.g. 1-16 or 8,21,23") from None
    if not out:
        raise ValueError("--areas: name the sub-areas, e.g. 1-16")
    return list(dict.fromkeys(out))  # each once, in the order given
