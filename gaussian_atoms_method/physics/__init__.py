"""The physics of a tilt series, in torch and numpy only.

* :mod:`.geometry`: detector axes of a tilt, pixel centres, the tilt-axis conventions;
* :mod:`.projector`: line integrals of isotropic (and anisotropic) 3D Gaussians onto a detector,
  dense, tiled and gsplat-tiled, all exact to float32;
* :mod:`.reconstruction`: filtered back-projection and SART of a single-axis series, slice by
  slice (the start's back-projection and the baselines' volumes);
* :mod:`.units`: the normalised units training runs in, and back to Å.

Nothing here imports nerfstudio or any other part of the package.
"""

import warnings


def quiet_sparse_notes() -> None:
    """Hide torch's notes on its sparse tensors (CSR "in beta", invariant checks "implicitly
    disabled") where this package's physics or launch raised them: the back-projection's and the
    kernel warm-up's matrices are valid by construction, and the note (once a process) is nothing a user
    can act on.  The same words from a user's own code still show.  Installed at import."""
    warnings.filterwarnings(
        "ignore",
        message="Sparse (CSR tensor support is in beta|invariant checks are implicitly disabled)",
        category=UserWarning,
        module=r"gaussian_atoms_method\.(physics|launch)\.",
    )


quiet_sparse_notes()
