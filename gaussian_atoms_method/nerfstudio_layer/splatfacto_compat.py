"""splatfacto's per-Gaussian properties in our terms, and the viewer's atom cloud.

nerfstudio's viewer and exporters read every property of a splatfacto model when they start
(``scales``, ``quats``, ``opacities``, ``colors``, spherical-harmonic features); splatfacto's
own would look up parameters we do not have (ns-viewer crashed on them).  This base class
defines them from our parameters: widths, identity rotations, log-amplitudes in place of opacities,
colours by integrated mass.
"""

from __future__ import annotations

import numpy as np
import torch
from nerfstudio.models.splatfacto import SplatfactoModel

from gaussian_atoms_method.nerfstudio_layer.viewer import mass_colours
from gaussian_atoms_method.physics.projector import gaussian_mass


class SplatfactoCompat(SplatfactoModel):
    """splatfacto with its per-Gaussian properties in our terms: the base of
    :class:`~gaussian_atoms_method.nerfstudio_layer.model.GaussianAtomsModel`, whose fit
    (:class:`~gaussian_atoms_method.engine.fit.AtomFit`) provides ``gauss_params``, ``means``,
    ``sigmas``, ``amplitudes``, ``num_points``, ``_log_scales``, ``density`` and
    ``load_state_dict``."""

    @torch.no_grad()
    def _viewer_atoms(self) -> tuple[np.ndarray, np.ndarray, float]:
        """Positions (world units), integrated masses and a point size (the median width)."""
        sigmas = self.sigmas.detach().cpu()
        masses = gaussian_mass(sigmas, self.amplitudes.detach().cpu())
        size = float(sigmas.median()) if len(sigmas) else 0.01
        return self.means.detach().cpu().numpy(), masses.numpy(), size

    @property
    def scales(self) -> torch.Tensor:
        """(N, 3) log-widths, as splatfacto stores them."""
        return self._log_scales().expand(-1, 3)

    @property
    def quats(self) -> torch.Tensor:
        """(N, 4) rotations (identity for isotropic Gaussians)."""
        if "quats" in self.gauss_params:
            return self.gauss_params["quats"]
        return torch.tensor([1.0, 0.0, 0.0, 0.0], device=self.means.device).expand(self.num_points, 4)

    @property
    def opacities(self) -> torch.Tensor:
        """(N, 1) log-amplitudes: the nearest thing to an opacity (nothing is composited)."""
        return self.gauss_params["log_amplitudes"]

    @property
    def colors(self) -> torch.Tensor:
        """(N, 3) colours in [0, 1] by integrated mass (as the viewer's point cloud)."""
        _, masses, _ = self._viewer_atoms()
        return torch.as_tensor(mass_colours(masses) / 255.0, dtype=torch.float32)

    @property
    def features_dc(self) -> torch.Tensor:
        return self.colors

    @property
    def features_rest(self) -> torch.Tensor:
        return torch.zeros(self.num_points, 0, 3)

    @property
    def shs_0(self) -> torch.Tensor:
        return self.colors[:, None, :]

    @property
    def shs_rest(self) -> torch.Tensor:
        return self.features_rest
