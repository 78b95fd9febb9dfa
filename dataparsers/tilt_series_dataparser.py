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
from typing import Dict, Literal, Optional, Tuple, Type

import torch
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataParserConfig, DataparserOutputs
from nerfstudio.data.datasets.base_dataset import InputDataset
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.plugins.registry_dataparser import DataParserSpecification

from gaussian_atoms_method.engine.views import views_from_tilt_series
from gaussian_atoms_method.physics.units import DATA_RANGE, Normalisation, normalised_projections

from .errors import TiltSeriesError
from .tilt_series_format import TiltSeries, load_tilt_series


def cameras_from_tilt_series(series: TiltSeries, norm: Normalisation) -> Cameras:
    """Orthographic nerfstudio cameras, one per projection, in normalised units
    (:func:`gaussian_atoms_method.engine.views.views_from_tilt_series`'s views)."""
    views = views_from_tilt_series(series, norm)
    return Cameras(
        camera_to_worlds=views.camera_to_worlds,
        fx=views.fx,
        fy=views.fy,
        cx=views.cx,
        cy=views.cy,
        width=views.width,
        height=views.height,
        camera_type=CameraType.ORTHOPHOTO,
    )


@dataclass
class TiltSeriesDataParserConfig(DataParserConfig):
    """A tilt series directory (``tilt_series.json``) or explicit files."""

    _target: Type = field(default_factory=lambda: TiltSeriesDataParser)
    data: Path = Path("data/tilt_series")
    """Directory holding tilt_series.json (or the manifest file itself)."""
    projections: Optional[Path] = None
    """Projection stack (.npy/.npz, .tif, .mrc/.st/.ali, .emd/.h5, .mat), relative to data;
    overrides the manifest."""
    angles_deg: Optional[Path] = None
    """Tilt angles in degrees (text, IMOD .tlt/.rawtlt, .npy, .mat; N values or N x 3 Euler),
    relative to data; overrides the manifest."""
    pixel_size_A: Optional[float] = None
    """Pixel size in Å; overrides the manifest."""
    tilt_axis: Optional[Literal["x", "y"]] = None
    """World axis of the tilt (README: convention); overrides the manifest."""
    truth: Optional[Path] = None
    """True atoms (any ASE-readable file) for scoring; overrides the manifest."""
    dataset: Optional[str] = None
    """Variable (.mat, .npz) or dataset / EMD group (.h5, .emd) holding the projections, when the
    file holds several."""
    tilt_index_axis: Optional[int] = None
    """Array axis of the tilt index (default: the format's convention; last for MATLAB)."""
    angles_variable: Optional[str] = None
    """Variable of a .mat angle file that holds the angles, when it holds several."""
    centre_px: Optional[Tuple[float, float]] = None
    """Detector (row, col) of the tilt axis; default the middle. RESIRE/GENFIRE data: (n//2, n//2)."""
    tilt_axis_angle_deg: Optional[float] = None
    """Angle of the tilt axis in the images (degrees, counterclockwise with the rows pointing up,
    from the direction tilt-axis names); default the manifest's, an IMOD MRC header's, or 0."""

    species: Optional[str] = None
    """The specimen's elements, e.g. Ta or Fe,Pt: they set the shortest distance two atoms may
    keep (the hard core); without them it is read from the atoms found.  Overrides the manifest."""

    def load(self, data: Optional[Path] = None) -> TiltSeries:
        """The tilt series these options name (``data`` overrides the directory); raises
        :class:`~dataparsers.errors.TiltSeriesError` naming the file and the problem."""
        return load_tilt_series(
            self.data if data is None else data,
            self.projections,
            self.angles_deg,
            self.pixel_size_A,
            self.tilt_axis,
            self.truth,
            self.dataset,
            self.tilt_index_axis,
            self.angles_variable,
            self.centre_px,
            self.tilt_axis_angle_deg,
            self.species,
        )


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
        norm, scaled = normalised_projections(series)
        projections = torch.from_numpy(scaled)
        cameras = cameras_from_tilt_series(series, norm)
        # Tomography has no held-out views: every split serves all projections.
        return DataparserOutputs(
            image_filenames=[Path(f"{series.source}#{i}") for i in range(series.n_views)],
            cameras=cameras,
            scene_box=SceneBox(aabb=torch.tensor([[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]])),
            metadata={
                "projections": projections,
                "normalisation": norm,
                "pixel_size_A": series.pixel_size_A,
                "truth_path": series.truth_path,
                "tilt_series": series,
                # Lets the model recognise a training view (per-view background and alignment).
                "view_c2w": cameras.camera_to_worlds.clone(),
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
