"""The fit's views and the dataparser's nerfstudio cameras are the same numbers."""

import numpy as np
import torch

from dataparsers.tilt_series_dataparser import cameras_from_tilt_series
from dataparsers.tilt_series_format import TiltSeries
from gaussian_atoms_method.engine.rendering import pixel_coordinates
from gaussian_atoms_method.engine.views import views_from_tilt_series
from gaussian_atoms_method.physics.units import Normalisation


def test_views_are_the_dataparsers_cameras_field_by_field():
    """Every field the fit reads, whole and sliced, and the detector coordinates and view
    index the renderer takes from them (off-centre tilt centre, a turned tilt axis)."""
    series = TiltSeries(
        projections=np.random.default_rng(0).uniform(size=(5, 12, 9)).astype(np.float32),
        angles_deg=np.linspace(-60.0, 60.0, 5),
        pixel_size_A=0.3,
        centre_px=(5.0, 3.5),
        tilt_axis_angle_deg=7.0,
    )
    norm = Normalisation(length_scale=0.2, data_scale=1.0)
    views, cameras = views_from_tilt_series(series, norm), cameras_from_tilt_series(series, norm)
    for name in ("camera_to_worlds", "fx", "fy", "cx", "cy", "width", "height", "camera_type"):
        assert torch.equal(getattr(views, name), getattr(cameras, name)), name
    assert len(views) == 5
    for v in range(5):
        a, b = views[v : v + 1], cameras[v : v + 1]
        for got, want in zip(pixel_coordinates(a, a.camera_to_worlds[0], False, "cpu", torch.float64),
                             pixel_coordinates(b, b.camera_to_worlds[0], False, "cpu", torch.float64)):  # fmt: skip
            assert torch.equal(got, want)
        assert torch.equal(a.camera_to_worlds, b.camera_to_worlds)
