"""A tilt series' views as orthographic detectors: the pose, pixel pitch and tilt centre of each.

The fields are those of nerfstudio's ``Cameras`` that the fit reads, in the same shapes, so the
fit renders either (:mod:`gaussian_atoms_method.engine.rendering` reads a camera by its
fields).  The tilt-series dataparser makes its nerfstudio cameras from these.

Conventions: a camera looks along its -z axis with x to the right and y up; the detector rows
run downwards, so the camera-to-world rotation has columns ``(cols, -rows, beam)`` of the
detector's orientation (:mod:`gaussian_atoms_method.physics.geometry`).  ``fx = fy`` is the
number of pixels per normalised length and ``(cx, cy)`` the point the tilt centre projects to,
in pixel-corner coordinates (``centre_px + 0.5``), so pixel ``(i, j)`` lies at detector
coordinates ``((i + 0.5 - cy) / fy, (j + 0.5 - cx) / fx)``.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import torch

from gaussian_atoms_method.engine.rendering import ORTHOGRAPHIC_CAMERA, VIEW_KEY
from gaussian_atoms_method.physics.units import Normalisation


@dataclass
class OrthographicViews:
    """V orthographic views: ``camera_to_worlds`` (V, 3, 4); ``fx``, ``fy``, ``cx``, ``cy``
    (V, 1) float; ``width``, ``height``, ``camera_type`` (V, 1) int; ``metadata`` as nerfstudio's
    (its tensors, (V, ...), are sliced with the views, and stay on the host: the view index,
    :data:`~.rendering.VIEW_KEY`, is read without waiting for a GPU)."""

    camera_to_worlds: torch.Tensor
    fx: torch.Tensor
    fy: torch.Tensor
    cx: torch.Tensor
    cy: torch.Tensor
    width: torch.Tensor
    height: torch.Tensor
    camera_type: torch.Tensor
    metadata: dict | None = None

    def __len__(self) -> int:
        return self.camera_to_worlds.shape[0]

    @property
    def shape(self) -> tuple[int]:
        return (len(self),)

    def __getitem__(self, index) -> OrthographicViews:
        """The views ``index`` selects (a slice keeps the leading axis, as nerfstudio's do)."""
        index = index if isinstance(index, slice) else slice(index, index + 1)
        tensors = {f.name: getattr(self, f.name)[index] for f in fields(self) if f.name != "metadata"}
        metadata = None if self.metadata is None else {
            k: v[index] if isinstance(v, torch.Tensor) else v for k, v in self.metadata.items()
        }  # fmt: skip
        return OrthographicViews(**tensors, metadata=metadata)

    def to(self, device) -> OrthographicViews:
        tensors = {f.name: getattr(self, f.name).to(device) for f in fields(self) if f.name != "metadata"}
        return replace(self, **tensors)


def views_from_tilt_series(series, norm: Normalisation) -> OrthographicViews:
    """One orthographic view per projection of ``series`` (a
    :class:`~dataparsers.tilt_series_format.TiltSeries`), in the normalised units of ``norm``."""
    axes = torch.from_numpy(series.detector_axes()).float()
    rows, cols, beam = axes[:, 0], axes[:, 1], axes[:, 2]
    n = series.n_views
    c2w = torch.zeros(n, 3, 4)
    c2w[:, :, 0], c2w[:, :, 1], c2w[:, :, 2] = cols, -rows, beam
    c2w[:, :, 3] = beam  # one normalised unit upstream of the centre: outside the volume
    h, w = series.image_shape
    pixels_per_unit = 1.0 / (series.pixel_size_A * norm.length_scale)

    def column(value, dtype=torch.float32):
        return torch.full((n, 1), value, dtype=dtype)

    return OrthographicViews(
        camera_to_worlds=c2w,
        fx=column(pixels_per_unit),
        fy=column(pixels_per_unit),
        cx=column(float(series.centre_px[1]) + 0.5),
        cy=column(float(series.centre_px[0]) + 0.5),
        width=column(w, torch.int64),
        height=column(h, torch.int64),
        camera_type=column(ORTHOGRAPHIC_CAMERA, torch.int64),
        metadata={VIEW_KEY: torch.arange(n)[:, None]},  # each view's index
    )
