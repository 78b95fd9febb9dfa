"""The ASTRA toolbox's reconstructions as benchmark rows: what a tomography user runs instead.

ASTRA (``pip install astra-toolbox``, our optional extra ``[astra]``) reconstructs a
single-axis tilt series slice by slice with its 2D parallel-beam algorithms: FBP and SIRT on
the CPU, FBP_CUDA and SIRT_CUDA on a GPU where its CUDA libraries load (the CUDA 12 runtime and
cuFFT 11).  The slices are our sinograms (:func:`~gaussian_atoms_method.physics.reconstruction.slice_sinograms`:
tilt centre at ``L // 2`` of an odd ``L``, ASTRA's detector centre too); with the angles as
given and ASTRA's ``linear`` projector its FBP slice equals scikit-image's orientation (what
differs from our FBP is the filter's windowing), so
:func:`~gaussian_atoms_method.physics.reconstruction.slices_to_volume` places it and the same
tracing scores it.
"""

from __future__ import annotations

import numpy as np


def astra_unavailable(gpu: bool) -> str | None:
    """None when ASTRA (and, with ``gpu``, its CUDA algorithms) can run here; else one line
    saying why not."""
    try:
        import astra
    except ImportError:
        return "ASTRA rows skipped: astra-toolbox is not installed (pip install 'gaussian-atoms[astra]')"
    if gpu:
        try:
            usable = bool(astra.use_cuda())
        except Exception as exc:  # its CUDA libraries fail to load
            return f"ASTRA CUDA rows skipped: {' '.join(str(exc).split())[:160]}"
        if not usable:
            return (
                "ASTRA CUDA rows skipped: astra.use_cuda() is False (no GPU, or its CUDA 12 runtime and cuFFT 11 do "
                "not load)"
            )
    return None


def astra_slices(sinograms: np.ndarray, angles_deg: np.ndarray, method: str, iterations=(1,), gpu: bool = False):
    """Reconstruct each (L, N) sinogram of ``sinograms`` (S, L, N) with ASTRA.

    Parameters
    ----------
    method : {"fbp", "sirt"}
    iterations : iterable of int
        SIRT: yield the slices after each of these iteration counts (increasing), each run
        continuing from the last; FBP: ignored (one result).
    gpu : bool
        ASTRA's CUDA algorithms instead of its CPU ones.

    Yields
    ------
    (iterations done, (S, L, L) array) in scikit-image's slice orientation; SIRT with ASTRA's
    ``MinConstraint`` 0 (a potential is not negative), as our
    :func:`~gaussian_atoms_method.physics.reconstruction.sirt`.
    """
    import astra

    if method not in ("fbp", "sirt"):
        raise ValueError(f"method must be 'fbp' or 'sirt', got {method!r}")
    n_slices, length, _ = sinograms.shape
    volume_geometry = astra.create_vol_geom(length, length)
    projection_geometry = astra.create_proj_geom(
        "parallel", 1.0, length, np.deg2rad(np.asarray(angles_deg, dtype=np.float64))
    )
    projector = astra.create_projector("cuda" if gpu else "linear", projection_geometry, volume_geometry)
    name = {"fbp": "FBP", "sirt": "SIRT"}[method] + ("_CUDA" if gpu else "")
    slices = []
    try:
        for sino in sinograms:
            sino_id = astra.data2d.create("-sino", projection_geometry, np.ascontiguousarray(sino.T, dtype=np.float32))
            rec_id = astra.data2d.create("-vol", volume_geometry, 0.0)
            config = astra.astra_dict(name)
            config.update(ReconstructionDataId=rec_id, ProjectionDataId=sino_id, ProjectorId=projector)
            if method == "sirt":
                config["option"] = {"MinConstraint": 0.0}
            slices.append((astra.algorithm.create(config), sino_id, rec_id))
        done = 0
        for target in [1] if method == "fbp" else iterations:
            for algorithm, _, _ in slices:
                astra.algorithm.run(algorithm, 1 if method == "fbp" else int(target) - done)
            done = 1 if method == "fbp" else max(done, int(target))
            yield done, np.stack([astra.data2d.get(rec_id) for _, _, rec_id in slices])
    finally:
        for algorithm, sino_id, rec_id in slices:
            astra.algorithm.delete(algorithm)
            astra.data2d.delete([sino_id, rec_id])
        astra.projector.delete(projector)
