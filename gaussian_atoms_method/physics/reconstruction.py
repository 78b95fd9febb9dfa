"""Voxel baselines: filtered back-projection and SART, slice by slice along the tilt axis.

FBP (:func:`filtered_backprojection`, equal to scikit-image's ``iradon``) and scikit-image's
``iradon_sart`` reconstruct each slice perpendicular to the tilt axis.  Conventions (checked
in the tests against our projector): with ``theta = +angle`` the reconstructed slice ``rec[r, c]`` holds the point at
in-plane coordinate ``c`` (detector
direction at zero tilt) and depth ``z = r``, both about index ``L // 2``; scikit-image puts the
rotation axis at detector index ``L // 2``, so each sinogram is padded to an odd length and
shifted (cubic spline) to bring our tilt centre (``centre_px``) there.  Values are returned in
projection units per Å (V for projected potentials in V·Å).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy

from gaussian_atoms_method.physics.devices import HOST
from gaussian_atoms_method.physics.fbp_filters import even_filter, filter_matrix
from gaussian_atoms_method.physics.geometry import to_nominal_axis


@dataclass
class Volume:
    """A reconstructed volume ``data[x, y, z]`` on a regular grid.

    Attributes
    ----------
    data : (X, Y, Z) float array
    spacing_A : float
        Voxel size, Å.
    origin_index : (3,) float array
        Fractional voxel index of the tilt centre (the coordinate origin before ``origin_A``).
    """

    data: np.ndarray
    spacing_A: float
    origin_index: np.ndarray

    def index_to_A(self, index: np.ndarray) -> np.ndarray:
        """(M, 3) fractional voxel indices -> (M, 3) positions in Å about the tilt centre."""
        return (np.asarray(index, dtype=np.float64) - self.origin_index) * self.spacing_A

    def resample(self, shape, voxel_size_A: float) -> np.ndarray:
        """Values on a centred grid of ``shape`` (voxel ``i`` at ``(i - (n - 1) / 2) * voxel_size_A``
        about the tilt centre), by trilinear interpolation; zero outside this volume."""
        axes = [
            (np.arange(n) - (n - 1) / 2) * voxel_size_A / self.spacing_A + self.origin_index[a]
            for a, n in enumerate(shape)
        ]
        return scipy.ndimage.map_coordinates(self.data, np.meshgrid(*axes, indexing="ij"), order=1, mode="constant")


def _centred_sinograms(projections: np.ndarray, centre_index: float, axis: int) -> tuple[np.ndarray, int]:
    """Sinograms ``(S, L, N)`` for each slice along ``axis`` of the detector (1 rows, 2 cols),
    padded to odd length ``L`` with the tilt centre moved to index ``L // 2``."""
    n_views = projections.shape[0]
    across = projections.shape[3 - axis]  # the detector direction inside a slice
    length = across + 1 if across % 2 == 0 else across
    stack = np.moveaxis(projections, axis, 0)  # (S, N, across) for axis=2 -> (W, N, H)
    sino = np.zeros((stack.shape[0], length, n_views), dtype=np.float64)
    sino[:, :across, :] = np.swapaxes(stack, 1, 2)
    shift = length // 2 - centre_index
    if abs(shift) > 1e-9:
        sino = np.matmul(shift_matrix(length, shift), sino)
    return sino, length


def shift_matrix(length: int, shift_px: float) -> np.ndarray:
    """(length, length): scipy's cubic-spline shift of a 1D signal by ``shift_px`` (``order=3``,
    ``mode="constant"``) as a matrix, row ``i`` giving output sample ``i``.  The shift is linear,
    so a stack of sinograms shifted along one axis is one product with it: to rounding the same
    as ``scipy.ndimage.shift`` of the whole stack, whose 3D spline interpolates along the two
    unshifted axes too."""
    columns = [scipy.ndimage.shift(e, shift_px, order=3, mode="constant") for e in np.eye(length)]
    return np.stack(columns, axis=1)


def backprojection_matrix(
    angles_deg: np.ndarray, length: int, size: int, rows: slice | None = None, dtype=None, device="cpu"
):
    """scikit-image's linear-interpolation back-projection as a sparse matrix.

    Output pixel ``p = i * size + j`` of a ``size x size`` slice (centre ``size // 2``) reads,
    for each angle ``k``, the filtered projection at detector position ``t`` between samples
    ``i0`` and ``i0 + 1`` with weights ``1 - w`` and ``w``: two entries per pixel and angle.
    Columns index ``k * (length + 1) + detector``; the extra last detector sample of each angle
    is a zero that pixels whose ray misses the detector read (``np.interp(left=0, right=0)``).
    Built in torch on ``device`` (not in numpy and copied); the angles' cosines and sines are
    numpy's, so the entries are the same on every device.

    Parameters
    ----------
    angles_deg : (N,) array
    length : int
        Detector samples per angle (centre at ``length // 2``).
    size : int
        Side of the output slice, pixels.
    rows : slice, optional
        Only these output pixels (rows of the matrix); default all ``size**2``.
    dtype : torch dtype, optional
        Of the weights (default float64).
    device : torch device

    Returns
    -------
    torch.sparse_csr_tensor, shape (rows, N * (length + 1)), on ``device``
    """
    import torch

    start, stop, _ = (rows if rows is not None else slice(None)).indices(size * size)
    pixels = torch.arange(start, stop, device=device)
    radius = size // 2
    x = (pixels // size - radius).double()[:, None]  # output row
    y = (pixels % size - radius).double()[:, None]  # output column
    angles = np.deg2rad(np.asarray(angles_deg, dtype=np.float64))
    cos, sin = (torch.as_tensor(f(angles), device=device)[None, :] for f in (np.cos, np.sin))
    t = y * cos - x * sin + length // 2  # (P, N) detector position
    inside = (t >= 0) & (t <= length - 1)
    floor = torch.floor(t)
    i0 = torch.where(inside, floor, float(length)).long()  # misses read the zero sample
    w = torch.where(inside, t - floor, 0.0)
    block = torch.arange(len(angles), device=device)[None, :] * (length + 1)
    cols = torch.stack([block + i0, block + torch.clamp(i0 + 1, max=length)], dim=-1)  # (P, N, 2), sorted
    vals = torch.stack([1.0 - w, w], dim=-1).to(dtype or torch.float64)
    crow = torch.arange(len(pixels) + 1, device=device) * (2 * len(angles))
    return torch.sparse_csr_tensor(  # torch's note on it is hidden (physics/__init__)
        crow,
        cols.reshape(-1),
        vals.reshape(-1),
        size=(len(pixels), len(angles) * (length + 1)),
        check_invariants=False,
    )


def backproject_in_order(filtered, angles_deg: np.ndarray, length: int, size: int, rows: slice, out) -> None:
    """``out = backprojection_matrix(angles_deg, length, size, rows) @ filtered`` ((P, S), in
    place; ``filtered`` (N * (length + 1), S)), summed angle by angle in one fixed order, so the
    same input gives the same bits on every run: cuSPARSE's product of the matrix does not (four
    products on an H200, four results; a GPU run's start differed between processes)."""
    import torch

    start, stop, _ = rows.indices(size * size)
    pixels = torch.arange(start, stop, device=filtered.device)
    radius = size // 2
    x = (pixels // size - radius).double()
    y = (pixels % size - radius).double()
    out.zero_()
    angles = np.deg2rad(np.asarray(angles_deg, dtype=np.float64))
    for k, (cos, sin) in enumerate(zip(np.cos(angles), np.sin(angles))):
        t = y * float(cos) - x * float(sin) + length // 2
        inside = (t >= 0) & (t <= length - 1)
        floor = torch.floor(t)
        i0 = torch.where(inside, floor, float(length)).long()  # misses read the zero sample
        w = torch.where(inside, t - floor, 0.0).to(out.dtype)[:, None]
        block = k * (length + 1)
        out.addcmul_(filtered.index_select(0, block + i0), 1.0 - w)
        out.addcmul_(filtered.index_select(0, block + torch.clamp(i0 + 1, max=length)), w)


def _on_host(device) -> bool:
    """Whether ``device`` (a name or a torch device) is the CPU: the FBP runs in numpy and scipy there."""
    return str(device) == "cpu"


def backprojection_matrix_on_host(
    angles_deg: np.ndarray, length: int, size: int, rows: slice | None = None, dtype=np.float64
):
    """:func:`backprojection_matrix` built in numpy as a ``scipy.sparse`` CSR matrix of ``dtype``
    (the same entries: the same float64 operations), without torch."""
    from scipy import sparse

    start, stop, _ = (rows if rows is not None else slice(None)).indices(size * size)
    pixels = np.arange(start, stop)
    radius = size // 2
    x = (pixels // size - radius).astype(np.float64)[:, None]
    y = (pixels % size - radius).astype(np.float64)[:, None]
    angles = np.deg2rad(np.asarray(angles_deg, dtype=np.float64))
    t = y * np.cos(angles)[None, :] - x * np.sin(angles)[None, :] + length // 2
    inside = (t >= 0) & (t <= length - 1)
    floor = np.floor(t)
    i0 = np.where(inside, floor, float(length)).astype(np.int64)
    w = np.where(inside, t - floor, 0.0)
    block = np.arange(len(angles))[None, :] * (length + 1)
    cols = np.stack([block + i0, block + np.minimum(i0 + 1, length)], axis=-1)
    vals = np.stack([1.0 - w, w], axis=-1).astype(dtype)
    crow = np.arange(len(pixels) + 1) * (2 * len(angles))
    return sparse.csr_matrix(
        (vals.reshape(-1), cols.reshape(-1), crow), shape=(len(pixels), len(angles) * (length + 1))
    )


def _numpy_dtype(dtype):
    """A torch or numpy float dtype (None: float64) as numpy's."""
    return np.float32 if dtype is not None and "float32" in str(dtype) else np.float64


def filtered_backprojection(
    sinograms: np.ndarray,
    angles_deg: np.ndarray,
    filter_name: str = "ramp",
    output_size: int | None = None,
    device: str = "cpu",
    max_matrix_entries: int = 1 << 24,
    dtype=None,
    as_tensor: bool = False,
):
    """scikit-image's ``iradon`` (``circle=False``, linear interpolation) for a stack of
    sinograms at once, in torch.

    Every slice samples its filtered projections at the same detector positions, so the
    back-projection is one sparse matrix (:func:`backprojection_matrix`, two entries per
    output pixel and angle) applied to all slices' filtered projections at once, instead of
    scikit-image's per-slice loop of interpolations, in blocks of output rows to bound its
    memory.  On the CPU it runs in numpy and scipy as a sparse product (without importing torch:
    a start begun while the launcher imports it); elsewhere as gathers summed angle by angle
    (:func:`backproject_in_order`: cuSPARSE's product differs between runs).

    Parameters
    ----------
    sinograms : (S, L, N) array
        One sinogram per slice: L detector positions (centre at ``L // 2``), N angles.
    angles_deg : (N,) array
    filter_name : scikit-image filter name ("ramp", "hann", ...)
    output_size : int, default L
    device : torch device ("cpu", "cuda")
    max_matrix_entries : int
        Work in blocks of output pixels with at most this many matrix entries (two per pixel
        and angle).
    dtype : torch or numpy dtype, optional
        Of the product and the result (default float64, ``iradon``'s to rounding).  float32
        for a start that only looks for its maxima: its product and copies take less than half the time.
    as_tensor : bool
        Return the tensor on ``device`` rather than a host array.

    Returns
    -------
    (S, output_size, output_size) array (or tensor), equal to ``iradon`` of each slice.
    """
    sinograms = np.asarray(sinograms, dtype=np.float64)
    n_slices, length, n_angles = sinograms.shape
    if n_angles != len(angles_deg):
        raise ValueError(f"{n_angles} sinogram angles but {len(angles_deg)} angles_deg")
    size = length if output_size is None else int(output_size)
    # half the spectrum, along a contiguous axis
    padded, even = even_filter(length, filter_name)
    block = max(1, max_matrix_entries // (2 * n_angles))  # output pixels per block
    if _on_host(device):
        out = _backproject_on_host(sinograms, angles_deg, even, padded, size, block, _numpy_dtype(dtype))
        if not as_tensor:
            return out
        import torch

        return torch.from_numpy(out)
    import torch

    dtype = torch.float32 if _numpy_dtype(dtype) is np.float32 else torch.float64
    sino = torch.as_tensor(sinograms, device=device, dtype=dtype)
    # (N, S, L): the filter as one matrix product (cuBLAS) in the result's precision, not an FFT
    # (cuFFT's first use in a process costs a GPU run 0.25 s or more; the product is microseconds)
    matrix = torch.as_tensor(filter_matrix(even, padded, length, n_angles), device=device, dtype=dtype)
    filtered = sino.permute(2, 0, 1) @ matrix
    # One zero sample after each angle's detector (read by rays that miss it).
    filtered = torch.nn.functional.pad(filtered.transpose(1, 2), (0, 0, 0, 1)).reshape(
        n_angles * (length + 1), n_slices
    )
    out = torch.empty(size * size, n_slices, dtype=dtype, device=device)
    for start in range(0, size * size, block):
        rows = slice(start, min(start + block, size * size))
        backproject_in_order(filtered, angles_deg, length, size, rows, out[rows])
    out = out.T.reshape(n_slices, size, size)
    return out if as_tensor else out.cpu().numpy()


def _backproject_on_host(
    sinograms: np.ndarray, angles_deg, even_filter: np.ndarray, padded: int, size: int, block: int, dtype
) -> np.ndarray:
    """:func:`filtered_backprojection`'s filter and product in numpy and scipy, without torch
    (a start begun while the launcher imports it, :mod:`gaussian_atoms_method.launch.start_ahead`):
    scipy's sparse product gives torch's to the bit (the Au series in float32), on one core."""
    import scipy.fft

    n_slices, length, n_angles = sinograms.shape
    spectrum = scipy.fft.rfft(np.ascontiguousarray(sinograms.transpose(2, 0, 1)), n=padded, axis=-1)
    # (N, S, L)
    filtered = scipy.fft.irfft(spectrum * even_filter, n=padded, axis=-1)[..., :length] * (np.pi / (2 * n_angles))
    stacked = np.zeros((n_angles, length + 1, n_slices), dtype=dtype)  # one zero sample after each angle's detector
    stacked[:, :length, :] = filtered.transpose(0, 2, 1)
    stacked = stacked.reshape(n_angles * (length + 1), n_slices)
    out = np.empty((size * size, n_slices), dtype=dtype)
    for start in range(0, size * size, block):
        rows = slice(start, min(start + block, size * size))
        out[rows] = backprojection_matrix_on_host(angles_deg, length, size, rows, dtype) @ stacked
    return out.T.reshape(n_slices, size, size)


def reconstruct(
    projections: np.ndarray,
    angles_deg: np.ndarray,
    pixel_size_A: float,
    method: str = "sart",
    tilt_axis: str = "y",
    centre_px=None,
    sart_iterations: int = 1,
    filter_name: str = "ramp",
    device: str = "cpu",
    tilt_axis_angle_deg: float = 0.0,
    slice_size_px: int | None = None,
    dtype=None,
    as_tensor: bool = False,
) -> Volume:
    """FBP or SART reconstruction of a single-axis tilt series.

    Parameters
    ----------
    projections : (N, H, W) array
    angles_deg : (N,) array
    pixel_size_A : float
    method : {"fbp", "sart"}
        (SIRT on any device: :func:`sirt`.)
    tilt_axis : {"y", "x"}
    centre_px : (2,) floats, optional
        Detector (row, col) of the tilt centre; default the middle.
    sart_iterations : int
        SART sweeps (each over all angles).
    filter_name : str
        FBP filter (scikit-image names).
    device : str
        Torch device of the FBP (:func:`filtered_backprojection`); SART is scikit-image's.
    tilt_axis_angle_deg : float
        Angle of the tilt axis in the images (:mod:`.geometry`); the projections are first
        resampled (linear) so that it lies along the detector direction ``tilt_axis`` names.
    slice_size_px : int, optional
        FBP only: side of each reconstructed slice (perpendicular to the tilt axis), default the
        detector's length across the axis; larger for an object wider than the field of view
        (:mod:`.field_of_view`), whose voxels beyond the detector see only the views whose rays
        reach them.
    dtype, as_tensor
        FBP only: the precision, and the volume as a tensor on ``device``
        (:func:`filtered_backprojection`).

    Returns
    -------
    Volume
        ``data[x, y, z]``, voxel size ``pixel_size_A``, values per Å.
    """
    if method not in ("fbp", "sart"):
        raise ValueError(f"method must be 'fbp' or 'sart', got {method!r}")
    sino, length, axis_centre = slice_sinograms(projections, tilt_axis, centre_px, tilt_axis_angle_deg)
    theta = np.asarray(angles_deg, dtype=np.float64)
    # odd: centre at size // 2
    size = length if slice_size_px is None or method != "fbp" else max(int(slice_size_px) | 1, length)
    if method == "fbp":
        recs = filtered_backprojection(sino, theta, filter_name, size, device, dtype=dtype, as_tensor=as_tensor)
    else:
        from skimage.transform import iradon_sart  # not on an FBP's path: 0.1 s to import

        recs = []
        for s in sino:
            rec = None
            for _ in range(max(1, sart_iterations)):
                rec = iradon_sart(s, theta=theta, image=rec)
            recs.append(rec)
        recs = np.asarray(recs)
    return slices_to_volume(recs, pixel_size_A, tilt_axis, axis_centre)


def backprojection_for_peaks(
    projections,
    angles_deg,
    pixel_size_A: float,
    tilt_axis: str = "y",
    centre_px=None,
    tilt_axis_angle_deg: float = 0.0,
    slice_size_px: int | None = None,
    device: str = "cpu",
) -> Volume:
    """The Hann FBP a search for atom-like peaks reads (the start's step 1,
    :func:`gaussian_atoms_method.atoms.candidates.backprojection_candidates`), in float32
    (float64 takes twice as long on a CPU): a tensor on ``device`` (the filters and the maxima run there), or
    with ``device`` :data:`~gaussian_atoms_method.physics.devices.HOST` an array made without
    importing torch (the CPU's own FBP: the same values)."""
    on_host = device == HOST
    return reconstruct(
        projections,
        angles_deg,
        pixel_size_A,
        "fbp",
        tilt_axis,
        centre_px,
        filter_name="hann",
        device="cpu" if on_host else device,
        tilt_axis_angle_deg=tilt_axis_angle_deg,
        slice_size_px=slice_size_px,
        dtype=np.float32,
        as_tensor=not on_host,
    )


def slice_sinograms(
    projections: np.ndarray, tilt_axis: str = "y", centre_px=None, tilt_axis_angle_deg: float = 0.0
) -> tuple[np.ndarray, int, float]:
    """The (S, L, N) sinograms of the slices perpendicular to the tilt axis, each padded to odd
    length ``L`` with the tilt centre at ``L // 2`` (the layout :func:`filtered_backprojection`,
    :func:`sirt` and scikit-image take), and the detector index of the tilt centre along the
    axis.  ``projections`` (N, H, W) are first resampled so that the tilt axis lies along the
    detector direction ``tilt_axis`` names (:mod:`.geometry`)."""
    projections = to_nominal_axis(np.asarray(projections, dtype=np.float64), tilt_axis_angle_deg, centre_px)
    _, h, w = projections.shape
    ci, cj = ((h - 1) / 2, (w - 1) / 2) if centre_px is None else centre_px
    # Slices are perpendicular to the tilt axis: for "y" each detector column j is one slice
    # whose in-plane detector coordinate runs along the rows (x), and vice versa.
    slice_axis, in_plane_centre, axis_centre = (2, ci, cj) if tilt_axis == "y" else (1, cj, ci)
    sino, length = _centred_sinograms(projections, in_plane_centre, slice_axis)
    return sino, length, float(axis_centre)


def slices_to_volume(recs, pixel_size_A: float, tilt_axis: str, axis_centre: float) -> Volume:
    """A :class:`Volume` (values per Å) from (S, size, size) reconstructed slices in
    scikit-image's orientation (``rec[depth, in-plane]``); an array stays an array, a tensor a
    tensor on its device."""
    size = recs.shape[-1]
    vol = recs.swapaxes(1, 2)  # (slice, in-plane, depth)
    if tilt_axis == "y":
        view = vol.swapaxes(0, 1)  # (x, y, z)
        origin = np.array([size // 2, axis_centre, size // 2], dtype=np.float64)
    else:
        view = vol  # (x, y, z) with x the slice axis
        origin = np.array([axis_centre, size // 2, size // 2], dtype=np.float64)
    # one pass: divided into a contiguous volume of the final layout
    if isinstance(view, np.ndarray):
        # in the volume's precision, as torch divides
        data = np.divide(view, view.dtype.type(pixel_size_A), out=np.empty(view.shape, dtype=view.dtype))
    else:
        data = _divide_contiguous(view, pixel_size_A)
    return Volume(data, float(pixel_size_A), origin)


def _divide_contiguous(view, divisor: float):
    """``view / divisor`` as a new contiguous tensor, in one pass."""
    import torch

    return torch.div(view, divisor, out=torch.empty(view.shape, dtype=view.dtype, device=view.device))


def sirt(sinograms: np.ndarray, angles_deg: np.ndarray, iterations, device: str = "cpu", min_value: float | None = 0.0):
    """SIRT (simultaneous iterative reconstruction) of a stack of sinograms at once, on
    ``device``: ``x <- x + C A^T R (b - A x)``, with ``R`` and ``C`` the inverse row and column
    sums of the projector ``A``.

    ``A`` is the transpose of :func:`backprojection_matrix` (the linear-interpolation
    back-projection FBP uses): each pixel's value is spread over the two detector samples either
    side of its ray, which is the adjoint of that interpolation.  So SIRT and FBP share one
    sparse matrix, built once on the device; each iteration is two sparse x dense products over
    every slice at once.  ASTRA's SIRT3D is the same iteration with a ray-driven projector.

    Parameters
    ----------
    sinograms : (S, L, N) array
        As :func:`slice_sinograms` gives them.
    angles_deg : (N,) array
    iterations : iterable of int
        Yield the reconstruction after each of these iteration counts (increasing).
    device : torch device
    min_value : float, optional
        Clip every iterate below at this (0: a potential is not negative, ASTRA's
        ``MinConstraint``); None: no constraint.

    Yields
    ------
    (iteration, (S, L, L) float32 tensor on ``device``), in scikit-image's slice orientation.
    """
    import torch

    sino = torch.as_tensor(np.asarray(sinograms, dtype=np.float32), device=device)
    n_slices, length, n_angles = sino.shape
    backproject = backprojection_matrix(angles_deg, length, length, dtype=torch.float32, device=device)
    project = backproject.to_sparse_coo().t().coalesce().to_sparse_csr()  # A = B^T
    measured = torch.nn.functional.pad(sino.permute(2, 1, 0), (0, 0, 0, 1)).reshape(n_angles * (length + 1), n_slices)
    ones = torch.ones(length * length, 1, device=device)
    rays = project @ ones  # each detector sample's sum of weights (A's row sums)
    rays[length :: length + 1] = 0.0  # the zero sample after each angle's detector is not a ray
    inv_rays = torch.where(rays > 0, 1.0 / rays.clamp_min(1e-12), torch.zeros_like(rays))
    hits = backproject @ torch.ones(n_angles * (length + 1), 1, device=device)  # A's column sums
    inv_hits = torch.where(hits > 0, 1.0 / hits.clamp_min(1e-12), torch.zeros_like(hits))
    x = torch.zeros(length * length, n_slices, device=device)
    done = 0
    for target in iterations:
        for _ in range(int(target) - done):
            x += inv_hits * (backproject @ (inv_rays * (measured - project @ x)))
            if min_value is not None:
                x.clamp_(min=min_value)
        done = max(done, int(target))
        yield done, x.T.reshape(n_slices, length, length)
