"""nerfstudio dataparser ``tilt-series``: tilt angles become orthographic cameras, and the
projections a float dataset served from memory (:class:`TiltSeriesDataset`: nerfstudio's default
opens image files as 8-bit RGB; a tilt series is one float channel with negative values).

Each projection becomes a ``CameraType.ORTHOPHOTO`` camera whose pose is the tilt rotation
(:mod:`gaussian_atoms_method.engine.views`: the conventions, and the same views for the fit).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, Literal, Type

from gaussian_atoms_method.launch.ns_train import asks_for_this_method
from gaussian_atoms_method.launch.quiet_warnings import quiet_third_party_warnings

if asks_for_this_method(sys.argv):  # ns-train loads this dataparser before it imports its models
    quiet_third_party_warnings()

import torch  # noqa: E402
from nerfstudio.cameras.cameras import Cameras, CameraType  # noqa: E402
from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataParserConfig, DataparserOutputs  # noqa: E402
from nerfstudio.data.datasets.base_dataset import InputDataset  # noqa: E402
from nerfstudio.data.scene_box import SceneBox  # noqa: E402
from nerfstudio.plugins.registry_dataparser import DataParserSpecification  # noqa: E402

from gaussian_atoms_method.engine.views import views_from_tilt_series  # noqa: E402
from gaussian_atoms_method.physics.units import DATA_RANGE, Normalisation  # noqa: E402

from .errors import TiltSeriesError  # noqa: E402
from .tilt_series_format import TiltSeries  # noqa: E402
from .tilt_series_options import TiltSeriesOptions  # noqa: E402


def cameras_from_tilt_series(series: TiltSeries, norm: Normalisation) -> Cameras:
    """Orthographic nerfstudio cameras, one per projection, in normalised units
    (:func:`gaussian_atoms_method.engine.views.views_from_tilt_series`'s views), each marked
    with its view's index (``metadata``, which nerfstudio's cameras slice with them)."""
    return cameras_of(views_from_tilt_series(series, norm))


def cameras_of(views) -> Cameras:
    """nerfstudio's cameras of the engine's :class:`~gaussian_atoms_method.engine.views.OrthographicViews`."""
    return Cameras(
        camera_to_worlds=views.camera_to_worlds,
        fx=views.fx,
        fy=views.fy,
        cx=views.cx,
        cy=views.cy,
        width=views.width,
        height=views.height,
        camera_type=CameraType.ORTHOPHOTO,
        metadata=dict(views.metadata),
    )


@dataclass
class TiltSeriesDataParserConfig(TiltSeriesOptions, DataParserConfig):
    """A tilt series directory (``tilt_series.json``) or explicit files."""

    _target: Type = field(default_factory=lambda: TiltSeriesDataParser)


@dataclass
class TiltSeriesDataParser(DataParser):
    """Reads a tilt series; every projection is used for training and for evaluation."""

    config: TiltSeriesDataParserConfig

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        try:
            series = self.config.load()
        except TiltSeriesError as exc:
            # As nerfstudio's own dataparsers do: say what is wrong and exit (ns-viewer, eval).
            print(f"gaussian-atoms: error: {exc}", file=sys.stderr)
            raise SystemExit(2) from None
        from gaussian_atoms_method.engine.run import view_set_of  # the engine's one normalisation

        view_set, views = view_set_of(series)
        # Tomography has no held-out views: every split serves all projections.
        return DataparserOutputs(
            image_filenames=[Path(f"{series.source}#{i}") for i in range(series.n_views)],
            cameras=cameras_of(views),
            scene_box=SceneBox(aabb=torch.tensor([[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]])),
            metadata={
                "projections": view_set.projections,
                "normalisation": view_set.normalisation,
                "pixel_size_A": view_set.pixel_size_A,
                "truth_path": view_set.truth_path,
                "tilt_series": series,
                "view_c2w": view_set.view_c2w,
            },
        )


tilt_series_dataparser = DataParserSpecification(
    config=TiltSeriesDataParserConfig(), description="AET tilt series (tilt_series.json directory)"
)


class TiltSeriesDataset(InputDataset):
    """Projections of a tilt series, normalised to the paper's [0, 256] scale."""

    exclude_batch_keys_from_device = ["image"]

    def __init__(self, dataparser_outputs, scale_factor: float = 1.0):
        if scale_factor != 1.0:
            raise ValueError("camera_res_scale_factor must be 1.0 for tilt series: projections are not resampled")
        super().__init__(dataparser_outputs, scale_factor)
        self.projections: torch.Tensor = dataparser_outputs.metadata["projections"]

    def __len__(self) -> int:
        return self.projections.shape[0]

    def get_image_float32(self, image_idx: int) -> torch.Tensor:
        return self.projections[image_idx][..., None]

    def get_data(self, image_idx: int, image_type: Literal["uint8", "float32"] = "float32") -> Dict:
        if image_type != "float32":
            raise ValueError("tilt series are served as float32 only; set cache_images_type to float32")
        return {"image_idx": image_idx, "image": self.get_image_float32(image_idx)}

    def __getitem__(self, image_idx: int) -> Dict:
        """For display only (nerfstudio's viewer draws each view's image on its camera
        frustum, as 8-bit RGB from ``image * 255``): the projection scaled to [0, 1] in three
        channels.  Training reads :meth:`get_data` (the full-image datamanager caches it)."""
        image = (self.get_image_float32(image_idx) / DATA_RANGE).clamp(0.0, 1.0).expand(-1, -1, 3)
        return {"image_idx": image_idx, "image": image}
