"""``tilt_series.json`` itself: its name, its keys, read and written atomically.  No numpy."""

from __future__ import annotations

import json
from pathlib import Path

from .errors import TiltSeriesError

MANIFEST = "tilt_series.json"

KNOWN_KEYS = frozenset(
    {
        "projections",
        "angles_deg",
        "pixel_size_A",
        "tilt_axis",
        "truth",
        "origin_A",
        "centre_px",
        "volume",
        "volume_voxel_size_A",
        "description",
        "simulation",
        "dataset",
        "tilt_index_axis",
        "angles_variable",
        "tilt_axis_angle_deg",
        "species",
        "euler_convention",
        "drop_views",
        "noise",
        "contrast",
    }
)
"""The keys a manifest may hold (:mod:`dataparsers.tilt_series_format` says what each means)."""


def read_manifest(path: Path) -> dict:
    """The manifest at ``path`` as a dict; :class:`TiltSeriesError` naming it where it is not a
    JSON object or holds a key not in :data:`KNOWN_KEYS` (a misspelt key would be ignored)."""
    try:
        manifest = json.loads(Path(path).read_text())
    except json.JSONDecodeError as exc:
        raise TiltSeriesError(f"{path}: not valid JSON ({exc})") from exc
    if not isinstance(manifest, dict):
        raise TiltSeriesError(f"{path}: expected a JSON object")
    unknown = set(manifest) - KNOWN_KEYS
    if unknown:
        raise TiltSeriesError(f"{path}: unknown key(s) {sorted(unknown)}; expected some of {sorted(KNOWN_KEYS)}")
    return manifest


def write_manifest(directory: Path, manifest: dict) -> None:
    """Write tilt_series.json through a temporary file: readers never see half a manifest."""
    tmp = directory / (MANIFEST + ".tmp")
    tmp.write_text(json.dumps(manifest, indent=2) + "\n")
    tmp.replace(directory / MANIFEST)


def update_manifest(directory: str | Path, **entries) -> None:
    """Add or replace entries of an existing tilt_series.json, atomically."""
    directory = Path(directory)
    manifest = json.loads((directory / MANIFEST).read_text())
    manifest.update(entries)
    write_manifest(directory, manifest)
