"""The atoms in nerfstudio's viewer: a point cloud, one point per Gaussian, coloured by mass.

nerfstudio's viewer shows what ``get_outputs`` renders for its camera (for us an orthographic
projection of the potential, see :meth:`GaussianAtomsModel.get_outputs`).  Atoms are easier to
inspect as points: :class:`AtomsInViewer` is a :class:`ViewerControl` (found by the viewer on
the model, like any custom viewer element) that draws the current Gaussians into the viewer's
scene when the viewer starts (``ns-viewer --load-config``) and again whenever the model asks
(during ``ns-train``, after each densify / prune / merge).  Colour: the viridis map of each
Gaussian's integrated mass (:func:`mass_colours`; heavier element = brighter).
"""

from __future__ import annotations

from typing import Callable

import numpy as np
from nerfstudio.viewer.viewer_elements import ViewerControl

#: nerfstudio's viewer draws the scene at 10x the world (normalised) coordinates.
VISER_SCALE = 10.0


def mass_colours(masses: np.ndarray) -> np.ndarray:
    """(N,) masses -> (N, 3) uint8 viridis colours, linear from zero mass (dark purple) to the
    98th percentile (yellow): one element looks uniform, a lighter element sits at its mass
    ratio (Fe in FePt near 0.4: teal), and a faint, doubtful Gaussian stands out dark."""
    from matplotlib import colormaps

    masses = np.asarray(masses, dtype=np.float64)
    if masses.size == 0:
        return np.zeros((0, 3), dtype=np.uint8)
    hi = 1.05 * float(np.percentile(masses, 98))
    scaled = np.clip(masses / hi, 0.0, 1.0) if hi > 0 else np.full_like(masses, 0.5)
    return (colormaps["viridis"](scaled)[:, :3] * 255).astype(np.uint8)


class AtomsInViewer(ViewerControl):
    """Keeps a point cloud of the atoms in the viewer's scene.

    Parameters
    ----------
    atoms : callable returning ``(positions (N, 3) world units, masses (N,), point size (world units))``
        Called from the viewer's threads as well as the training loop.
    """

    def __init__(self, atoms: Callable[[], tuple[np.ndarray, np.ndarray, float]]):
        self._atoms = atoms
        self._ready = False

    def _setup(self, viewer) -> None:
        super()._setup(viewer)
        self._ready = True
        self.refresh()

        @self.viser_server.on_client_connect
        def _frame_the_particle(client) -> None:
            # Start each browser looking at the atoms from outside the particle (the default
            # pose suits scenes a few world units across; ours is a fraction of one).
            positions, _, _ = self._atoms()
            if len(positions) == 0:
                return
            centre = np.median(positions, axis=0) * VISER_SCALE
            radius = max(float(np.percentile(np.linalg.norm(positions * VISER_SCALE - centre, axis=1), 95)), 1e-3)
            client.camera.position = centre + radius * np.array([2.2, -2.2, 1.6])
            client.camera.look_at = centre

    def refresh(self) -> None:
        """Redraw the atoms (a no-op until a viewer has started)."""
        if not self._ready:
            return
        positions, masses, point_size = self._atoms()
        self.viser_server.scene.add_point_cloud(
            "/gaussian_atoms/atoms",
            points=np.asarray(positions, dtype=np.float32) * VISER_SCALE,
            colors=mass_colours(masses),
            point_size=float(point_size) * VISER_SCALE,
            point_shape="circle",
        )


def viewer_command(load_config, host: str = "127.0.0.1", port: int | None = None):
    """nerfstudio's ``ns-viewer`` on a finished run (``config.yml``), listening on ``host``
    (127.0.0.1: this machine only) and ``port`` (None: nerfstudio's), built but not run."""
    from nerfstudio.scripts.viewer.run_viewer import RunViewer, ViewerConfigWithoutNumRays

    return RunViewer(
        load_config=load_config, viewer=ViewerConfigWithoutNumRays(websocket_host=host, websocket_port=port)
    )
