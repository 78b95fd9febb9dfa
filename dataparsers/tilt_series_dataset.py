"""An InputDataset that serves the projections as float tensors from memory.

nerfstudio's default dataset opens image files with PIL and returns 8-bit RGB; a tilt series is
one float channel with negative values allowed, so we keep the normalised stack in memory and
hand out ``(H, W, 1)`` float32 views of it.
"""

from __future__ import annotations

from typing import Dict, Literal

import torch
from nerfstudio.data.datasets.base_dataset import InputDataset

from gaussian_atoms_method.physics.units import DATA_RANGE


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
