"""The physics of a tilt series, in torch and numpy only.

* :mod:`.geometry`: detector axes of a tilt, pixel centres, the tilt-axis conventions;
* :mod:`.projector`: line integrals of isotropic (and anisotropic) 3D Gaussians onto a detector,
  dense, tiled and gsplat-tiled, all exact to float32;
* :mod:`.reconstruction`: filtered back-projection and SART of a single-axis series, slice by
  slice (the start's back-projection and the baselines' volumes);
* :mod:`.units`: the normalised units training runs in, and back to Å.

Nothing here imports nerfstudio or any other part of the package.
"""
