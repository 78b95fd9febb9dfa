"""Per-view rendering pieces of the model: detector geometry from nerfstudio cameras and the
corrections a measured view may need.

* the detector axes and pixel coordinates of a camera (orthographic, or the viewer's
  perspective camera projected with its magnification at the tilt centre);
* the coarse phase: 2 x 2-binned pixel centres and data (``coarse_steps``);
* a tilt-angle error (``refine_tilts``): the camera turned about the tilt axis;
* the per-view parameters (:func:`view_parameters`): an in-plane shift (``refine_alignment``),
  a tilt error (``refine_tilts``), a constant, plane or smooth background (``background``) and
  the point-spread function shared by all views (``psf``, :mod:`..physics.psf`);
* several views per step in one projector call (``views_per_step``).

Each is a small function on tensors; :meth:`GaussianAtomsModel.get_outputs
<gaussian_atoms_method.nerfstudio_layer.model.GaussianAtomsModel.get_outputs>` composes them.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch.nn import Parameter

from gaussian_atoms_method.atoms.view_prediction import gauge_free_shifts
from gaussian_atoms_method.engine.errors import OptionError
from gaussian_atoms_method.physics.projector import (
    covariances_from_scales_quats,
    project_anisotropic_gaussians,
    project_gaussians,
    project_gaussians_gsplat,
    project_gaussians_tiled,
)
from gaussian_atoms_method.physics.psf import KERNEL_WIDTHS_A, apply_kernel, kernel_margin_of, widened

ORTHOGRAPHIC_CAMERA = 8
"""The camera type of an orthographic view: nerfstudio's ``CameraType.ORTHOPHOTO`` value, the
type the tilt series' cameras have (``tests/test_rendering.py`` holds the two equal).  Cameras
are read by their fields (``height``, ``width``, ``fx``, ``fy``, ``cx``, ``cy``,
``camera_type``, ``camera_to_worlds``, ``metadata``), so any object that has them renders."""


def detector_axes(c2w: torch.Tensor) -> torch.Tensor:
    """(..., 2, 3) world directions of the detector rows and columns of nerfstudio camera
    poses (..., 3, 4): columns along the camera's x, rows down its y."""
    return torch.stack([-c2w[..., :, 1], c2w[..., :, 0]], dim=-2)


def binned_like(image: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """(H, W, C) ``image`` as is, or averaged over 2 x 2 blocks to the (H/2, W/2) of ``like``
    (:func:`binned_views` on its first two axes)."""
    h, w = like.shape[:2]
    if image.shape[:2] != (h, w):
        image = binned_views(image.movedim(-1, 0), h, w).movedim(0, -1)
    return image


def binned_views(images: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """(..., H, W) ``images`` as they are, or averaged over 2 x 2 blocks to (..., h, w) = (H/2,
    W/2), every view in one go.  The four strided quarters summed in pairs: the values of a
    reshaped ``mean`` over the blocks, to the bit in the tests, in a small part of its time on
    the CPU (a coarse training step bins four times)."""
    if images.shape[-2:] == (h, w):
        return images
    x = images[..., : 2 * h, : 2 * w]
    return ((x[..., 0::2, 0::2] + x[..., 0::2, 1::2]) + (x[..., 1::2, 0::2] + x[..., 1::2, 1::2])) * 0.25


def pixel_coordinates(camera, c2w: torch.Tensor, coarse: bool, device, dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """(H,) and (W,) detector coordinates (normalised lengths) of the pixel centres of one
    camera, along its rows and columns from the tilt centre.

    A perspective camera (the viewer's) is projected along its view direction with the
    magnification it has at the tilt centre, so zooming in and out works as expected.  With
    ``coarse`` the coordinates are those of the centres of 2 x 2 pixel blocks (the loss bins
    the data alike, :func:`binned_like`).
    """
    h, w = int(camera.height.item()), int(camera.width.item())
    rows = (torch.arange(h, device=device, dtype=dtype) + 0.5 - camera.cy[0, 0].to(dtype)) / camera.fy[0, 0].to(dtype)
    cols = (torch.arange(w, device=device, dtype=dtype) + 0.5 - camera.cx[0, 0].to(dtype)) / camera.fx[0, 0].to(dtype)
    if int(camera.camera_type[0, 0]) != ORTHOGRAPHIC_CAMERA:
        distance = torch.dot(c2w[:, 3], c2w[:, 2]).clamp_min(1e-3)
        rows, cols = rows * distance, cols * distance
    if coarse:
        h, w = h // 2, w // 2
        rows, cols = rows[: 2 * h].view(h, 2).mean(dim=1), cols[: 2 * w].view(w, 2).mean(dim=1)
    return rows, cols


def rotate_about(vectors: list[torch.Tensor], axis: torch.Tensor, angle: torch.Tensor) -> list[torch.Tensor]:
    """Each (3,) vector rotated by ``angle`` (radians) about the unit ``axis`` (Rodrigues).

    Used for a view's tilt-angle error: the whole camera turns about the tilt axis through the
    tilt centre (its detector axes and its position: otherwise its offset along the beam would
    leak into the image as a shift)."""
    c, s = torch.cos(angle), torch.sin(angle)
    return [v * c + torch.linalg.cross(axis, v) * s + axis * torch.dot(axis, v) * (1 - c) for v in vectors]


def add_background(
    image: torch.Tensor, coefficients: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor
) -> torch.Tensor:
    """(H, W) ``image`` plus a view's background: a constant (1 coefficient), a plane over the
    detector in normalised coordinates (3: constant, row slope, column slope) or a quadratic
    surface (6: those and the row^2, row x column and column^2 terms), :func:`floor_images`."""
    return image + floor_images(coefficients[None], coordinate_powers(rows, cols))[0]


FLOOR_TERMS = ((0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2))
"""The powers of the row and column coordinates each background coefficient multiplies, in
:func:`add_background`'s order (test_floors checks the two agree)."""

MAX_POWER = 4
"""The highest power of a coordinate the floors need: their terms go to 2, the products of two
terms in their normal equations (:mod:`.floors`) to 4."""


def coordinate_powers(rows: torch.Tensor, cols: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(5, H) and (5, W): the powers 0 to :data:`MAX_POWER` of the (H,) ``rows`` and (W,) ``cols``."""

    def powers(x):
        out = [torch.ones_like(x), x]
        while len(out) <= MAX_POWER:
            out.append(out[-1] * x)
        return torch.stack(out)

    return powers(rows), powers(cols)


def floor_images(coefficients: torch.Tensor, powers: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
    """(V, H, W) the floors of (V, K) ``coefficients`` (K of :data:`FLOOR_TERMS`' terms) over the
    detector whose :func:`coordinate_powers` are ``powers``: ``rows^a M cols^b`` summed, with
    each view's coefficients placed in a 3 x 3 matrix M.  Two matrix products for all of a step's
    views: the term-by-term sums took about 25 operations a view, each a kernel launch on a GPU."""
    row_powers, col_powers = powers
    k = coefficients.shape[-1]
    m = (coefficients @ _term_matrix(k, coefficients.device, coefficients.dtype)).view(-1, 3, 3)
    return row_powers[:3].T @ m @ col_powers[:3]


_TERM_MATRICES: dict = {}


def _term_matrix(k: int, device, dtype) -> torch.Tensor:
    """(K, 9): coefficient i to the entry (a, b) of the flattened 3 x 3 matrix, FLOOR_TERMS[i] = (a, b); made
    once per device, copied there without waiting for it (:func:`to_device_without_waiting`)."""
    key = (k, torch.device(device), dtype)
    if key not in _TERM_MATRICES:
        m = torch.zeros(k, 9, dtype=dtype)
        for i, (a, b) in enumerate(FLOOR_TERMS[:k]):
            m[i, 3 * a + b] = 1.0
        _TERM_MATRICES[key] = to_device_without_waiting(m, key[1])
    return _TERM_MATRICES[key]


def view_parameters(cfg, n_views: int, floor: float | None, surfaces, series, length_scale: float) -> tuple[dict, dict]:
    """The model's per-view parameters (name -> Parameter) and the buffers they need: a
    background (solved in closed form, :mod:`.floors`) starting at ``floor`` (on the (V, H, W)
    ``surfaces`` of a floor that varies within the views), the point-spread function's weights,
    shifts and tilt errors, as the options ask."""

    params, buffers = (
        {},
        {
            "background_surfaces": torch.as_tensor(
                surfaces if surfaces is not None else np.zeros((0, 1, 1)), dtype=torch.float32
            )
        },
    )
    background = cfg.background if cfg.background != "auto" else ("constant" if floor is not None else "none")
    if background != "none":
        # A floor that varies within the views starts on its frame's quadratic surface and gets
        # a quadratic correction over the whole detector: a surface read from a frame the object
        # reaches holds the object's tails (on the 20,000-atom a-Si the frame's upper 3-sigma
        # tail held 4 times its lower), and held fixed its misfit went to Gaussians in the vacuum.
        terms = 3 if background == "plane" else 6 if surfaces is not None else 1
        # solved, not learned (.floors)
        params["background"] = Parameter(torch.zeros(n_views, terms), requires_grad=False)
        params["background"].data[:, 0] = floor or 0.0
    if cfg.psf != "none":  # one kernel for every view: the microscope's
        # learned from psf_weights (zeros: the identity, no kernel until the data ask), or held there
        params["psf"] = Parameter(
            torch.tensor(cfg.psf_weights, dtype=torch.float32), requires_grad=cfg.psf == "learned"
        )
        buffers["psf_widths"] = torch.tensor(KERNEL_WIDTHS_A) * length_scale
    if cfg.refine_alignment:
        params["view_shifts"] = Parameter(torch.zeros(n_views, 2))
    if cfg.refine_gain:
        params["view_gains"] = Parameter(torch.zeros(n_views, 1))
    if cfg.refine_tilts:
        if series is None:
            raise OptionError(
                "--pipeline.model.refine-tilts needs a single-axis tilt series from the tilt-series dataparser"
            )
        params["view_tilts"] = Parameter(torch.zeros(n_views, 1))
        buffers["tilt_axis_vector"] = torch.tensor([0.0, 1.0, 0.0] if series.tilt_axis == "y" else [1.0, 0.0, 0.0])
    return params, buffers


def kernel_margin_px(model, pitch: float | None) -> int:
    """Pixels (of ``pitch``, normalised lengths) each side of a view is widened by before the
    kernel (:func:`~gaussian_atoms_method.physics.psf.kernel_margin_of`): 0 without a kernel, for a kernel held at the
    identity, and where nothing lies beyond the detector (no film: the volume is the field)."""
    density = getattr(model, "density", None)
    if pitch is None or "psf" not in model.view_params or density is None or density.field_half_extent is None:
        return 0
    if model.config.psf == "fixed" and not any(model.config.psf_weights):
        return 0
    return kernel_margin_of(model.psf_widths_host[0], pitch)


def projected_and_blurred(model, project, rows: torch.Tensor, cols: torch.Tensor, pitch: float | None) -> torch.Tensor:
    """(..., H, W) ``project(rows, cols)`` through the model's kernel (:func:`blur`), projected on
    a detector widened by :func:`kernel_margin_px` where matter lies beyond it, then cut back to
    ``rows`` x ``cols``."""
    margin = kernel_margin_px(model, pitch)
    if margin == 0:
        return blur(model, project(rows, cols), pitch)
    images = blur(model, project(widened(rows, margin, pitch), widened(cols, margin, pitch)), pitch)
    return images[..., margin:-margin, margin:-margin]


def blur(model, images: torch.Tensor, spacing: float | None) -> torch.Tensor:
    """(V, H, W) projections through the model's learned point-spread function, if it has one
    (``spacing``: the pixel pitch, normalised lengths; None for a single row; the kernel's
    widths are the model's ``psf_widths_host``, read once when its buffers were made)."""
    if "psf" not in model.view_params or spacing is None:
        return images
    # kept non-negative by project_weights after each step (psf held-out: read, not learned)
    return apply_kernel(images, spacing, model.psf_widths_host, model.view_params["psf"].to(images))


def one_view(
    model,
    c2w: torch.Tensor,
    view: int | None,
    rows: torch.Tensor,
    cols: torch.Tensor,
    pitch: float | None,
    means,
    sigmas,
    amplitudes,
) -> torch.Tensor:
    """(H, W) the model's projection for one camera from its own (3, 4) pose ``c2w`` (the
    viewer's, evaluation's, or a training view's with a learned shift or tilt error, or
    anisotropic Gaussians), blurred by the model's kernel."""
    dev, dt = means.device, means.dtype
    (rows_dir, cols_dir), t = detector_axes(c2w), c2w[:, 3]
    if view is not None and "view_tilts" in model.view_params:
        tilts = model.view_params["view_tilts"]  # the error relative to the mean (a common one rotates the particle)
        rows_dir, cols_dir, t = rotate_about(
            [rows_dir, cols_dir, t], model.tilt_axis_vector.to(dev, dt), (tilts[view, 0] - tilts[:, 0].mean()).to(dt)
        )
    axes = torch.stack([rows_dir, cols_dir])[None]
    if view is not None and "view_shifts" in model.view_params:  # the content sits shifted by s: evaluate at x - s
        shifts = model.view_params["view_shifts"].to(dt)
        s = gauge_free_shifts(shifts, detector_axes(model.view_c2w.to(dev, dt)))[view]
        rows, cols = rows - s[0], cols - s[1]
    gain = 1.0
    if view is not None and "view_gains" in model.view_params:
        gain = view_gain(model.view_params["view_gains"].to(dt), view)
    if model.config.isotropic:
        project = projector_for(model.config.projector, dev)
        return projected_and_blurred(
            model, lambda r, c: project(means - t, sigmas, amplitudes * gain, axes, r, c), rows, cols, pitch
        )[0]
    cov = covariances_from_scales_quats(model._log_scales(), model.gauss_params["quats"])
    return projected_and_blurred(
        model,
        lambda r, c: project_anisotropic_gaussians(model.means - t, cov, model.amplitudes * gain, axes, r, c),
        rows,
        cols,
        pitch,
    )[0]


def view_gain(log_gains: torch.Tensor, view: int) -> torch.Tensor:
    """View ``view``'s gain from the (V, 1) learned log gains, their mean taken out: a gain the
    same in every view scales the atoms' amplitudes, not the views.

    >>> g = torch.tensor([[0.1], [0.3], [-0.1]])
    >>> round(float(view_gain(g, 1)), 4), round(float(view_gain(g + 5.0, 1)), 4)
    (1.2214, 1.2214)
    """
    return torch.exp(log_gains[view, 0] - log_gains[:, 0].mean())


def view_floors(model, views, powers: tuple[torch.Tensor, torch.Tensor], dtype) -> torch.Tensor:
    """(V, H, W) the floors of the model's ``views`` (training view indices: a list, or a (V,)
    tensor on the model's device, :func:`step_index`) on the detector of
    :func:`coordinate_powers` ``powers``: each view's background and, for a floor that varies
    within the views, its surface (binned like the image in the coarse phase)."""
    coefficients = model.view_params["background"]
    index = index_on(views, coefficients.device)  # a device index passes as it is
    floors = floor_images(coefficients[index].to(dtype), powers)
    if len(model.background_surfaces):
        floors = floors + model.view_geometry.surfaces(model.background_surfaces, *floors.shape[-2:])[index].to(dtype)
    return floors


def add_view_floors(
    model, images: torch.Tensor, views, rows: torch.Tensor, cols: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """(V, H, W) ``images`` of the model's ``views`` plus their floors (:func:`view_floors`), and
    the floors; what was rendered is kept for the floors' closed-form solve
    (``model.rendered_floors``: the views, the detector's coordinate powers and the floors)."""
    powers = model.view_geometry.powers(rows, cols)
    floors = view_floors(model, views, powers, images.dtype)
    model.rendered_floors = (views, powers, floors.detach())
    return images + floors, floors


VIEW_KEY = "view"
"""The key of a camera's ``metadata`` that names its view, the index of its projection among the
fit's views (an int, or a one-element tensor): set where the views' cameras are made
(:func:`~.views.views_from_tilt_series`, the training loop, the nerfstudio adapter); a camera
without it (the viewer's) is no view, rendered without a view's floor, shift or gain."""


def view_of(camera) -> int | None:
    """The index of the view ``camera`` is (:data:`VIEW_KEY`), or None."""
    view = (camera.metadata or {}).get(VIEW_KEY)
    if isinstance(view, torch.Tensor):
        view = view.reshape(-1)[0]
    return None if view is None else int(view)


class ViewGeometry:
    """What a step reads from a view's camera that stays fixed for the run: its pixel
    coordinates, their pitch and their powers for the floors.  Reading a GPU camera's size or
    pose waits for the GPU (six waits a step, which kept the CPU from queueing the next step's
    work), so each view's camera is read once and then served from here, by its view
    (:func:`view_of`).  Other cameras (the viewer's) are read each time."""

    def __init__(self) -> None:
        self._seen: dict = {}  # (view, coarse, device, dtype) -> (rows, cols, pitch, view)
        self._powers: dict = {}  # id(rows), id(cols) -> (rows, cols, their coordinate_powers): found in one look
        self._surfaces: dict = {}  # (h, w) -> the floors' surfaces binned to (V, h, w)

    def read(self, camera, c2w: torch.Tensor, coarse: bool, device, dtype):
        """(rows, cols, pitch, view): :func:`pixel_coordinates`, the pitch of the rows as a float
        (None for a single row) and :func:`view_of` ``camera``."""
        view = view_of(camera)
        key = None if view is None else (view, coarse, str(device), dtype)
        if key in self._seen:
            return self._seen[key]
        rows, cols = pixel_coordinates(camera, c2w, coarse, device, dtype)
        found = (rows, cols, float(rows[1] - rows[0]) if len(rows) > 1 else None, view)
        if key is not None:
            self._seen[key] = found
        return found

    def powers(self, rows: torch.Tensor, cols: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """:func:`coordinate_powers` of ``rows`` and ``cols``, kept for the coordinates :meth:`read`
        keeps (others, a shifted view's or the viewer's, are computed each time)."""
        hit = self._powers.get((id(rows), id(cols)))
        if hit is not None and hit[0] is rows and hit[1] is cols:
            return hit[2]
        powers = coordinate_powers(rows, cols)
        if any(found[0] is rows and found[1] is cols for found in self._seen.values()):
            self._powers[(id(rows), id(cols))] = (rows, cols, powers)
        return powers

    def surfaces(self, surfaces: torch.Tensor, h: int, w: int) -> torch.Tensor:
        """The (V, H, W) ``surfaces`` binned to (V, h, w) (:func:`binned_views`), once per size."""
        if (h, w) not in self._surfaces:
            self._surfaces[(h, w)] = binned_views(surfaces, h, w)
        return self._surfaces[(h, w)]


def render_views(
    model, index, rows: torch.Tensor, cols: torch.Tensor, pitch: float | None, floors: bool = True
) -> torch.Tensor:
    """(V, H, W) the model's projections of its training ``views`` (a list, or a (V,) index on the
    model's device) in one projector call, on the detector of ``rows`` and ``cols``: the cameras
    on their beam axes through the tilt centre (``model.indexed_views``), blurred by the model's
    kernel, with their floors (``floors``)."""
    dev, dt = model.means.device, model.means.dtype
    index = index_on(index, dev)
    project, axes = projector_for(model.config.projector, dev), detector_axes(model.view_c2w[index].to(dev, dt))
    images = projected_and_blurred(
        model, lambda r, c: project(model.means, model.sigmas, model.amplitudes, axes, r, c), rows, cols, pitch
    )
    return (
        add_view_floors(model, images, index, rows, cols)[0] if floors and "background" in model.view_params else images
    )


RENDER_MEMORY_SHARE = 0.25
""":func:`view_chunks` spends at most this share of the free GPU memory (1 GiB on a CPU) on a
chunk of views rendered at once; the rest stays for what the run holds."""


def view_chunks(n_views: int, n_gaussians: int, h: int, w: int, device: torch.device) -> list[list[int]]:
    """The views 0..n_views-1 in consecutive chunks that :func:`render_views` can render at once:
    the dense projector holds about three (N, H + W) float32 arrays a view."""
    budget = RENDER_MEMORY_SHARE * torch.cuda.mem_get_info(device)[0] if device.type == "cuda" else 2.0**30
    size = max(1, int(budget // (12.0 * max(n_gaussians, 1) * (h + w))))
    return [list(range(i, min(i + size, n_views))) for i in range(0, n_views, size)]


def projector_name(option: str, device: torch.device) -> str:
    """The projector the ``projector`` option names on ``device`` ("auto": dense on CUDA, else tiled)."""
    return ("dense" if device.type == "cuda" else "tiled") if option == "auto" else option


def projector_for(option: str, device: torch.device):
    """The projector function the ``projector`` option names on ``device``; OptionError for gsplat off CUDA."""
    choice = projector_name(option, device)
    if choice == "gsplat" and device.type != "cuda":
        raise OptionError("--pipeline.model.projector gsplat needs a CUDA device; use auto, tiled or dense on CPU")
    return {"dense": project_gaussians, "tiled": project_gaussians_tiled, "gsplat": project_gaussians_gsplat}[choice]


def index_on(index, device: torch.device) -> torch.Tensor:
    """A host index (a list or a CPU tensor) as a tensor on ``device``, copied without waiting for
    the device: through pinned memory, asynchronously.  A plain copy to the GPU (``torch.tensor``
    of a list, or indexing a GPU tensor by a CPU one) waits for every queued kernel first; the
    floors' solve did that twice a step (``torch.cuda.set_sync_debug_mode``)."""
    return to_device_without_waiting(torch.as_tensor(index, dtype=torch.long), device)


def to_device_without_waiting(tensor: torch.Tensor, device: torch.device) -> torch.Tensor:
    """``tensor`` on ``device``; a host tensor bound for a GPU goes through pinned memory,
    asynchronously (:func:`index_on`), other moves are plain."""
    if torch.device(device).type != "cuda" or tensor.device.type != "cpu":  # nothing to pin: a plain move
        return tensor.to(device)
    return tensor.pin_memory().to(device, non_blocking=True)


class FiniteWatch:
    """Stops training with FloatingPointError naming the step and the cause when the loss or a
    parameter is not finite (parameters are checked too: the tiled projector skips a Gaussian
    whose centre is NaN, so the loss alone would not show it).

    On the CPU (and devices other than CUDA) each step is judged at once.  On a CUDA GPU,
    reading a flag waits for the GPU's queued work, so each step's counts are copied to the
    host without waiting and judged at the next step, once that copy has landed (:meth:`flush`
    judges the last one): a non-finite step still stops the run a step later, under its own
    step number."""

    def __init__(self) -> None:
        self._pending = None
        self.captured = None  # (counts, names, rows, measured) of a step being captured

    def check(self, loss: torch.Tensor, params, measured: torch.Tensor, step: int) -> None:
        """Judge (CPU) or queue (GPU) this step's loss and ``params`` (name -> (N, ...) tensor);
        ``measured`` is read only to name the cause."""
        names = list(params)
        # the loss, then each parameter's count of Gaussians whose values are all finite: ten small operations a step
        counts = torch.stack(
            [loss.detach().reshape(()).float()]
            + [torch.isfinite(p.detach()).flatten(1).all(-1).sum(dtype=torch.float32) for p in params.values()]
        )
        rows = [len(p) for p in params.values()]
        if counts.device.type != "cuda":  # the CPU (or another device): judged at once
            return self._judge(counts.tolist(), names, rows, measured, step)
        # a step captured as a CUDA graph: each replay queues them (.step_graph)
        if torch.cuda.is_current_stream_capturing():
            self.captured = (counts, names, rows, measured)
            return None
        return self.queue(counts, names, rows, measured, step)

    def queue(self, counts: torch.Tensor, names: list[str], rows: list[int], measured: torch.Tensor, step: int) -> None:
        """Copy a GPU step's ``counts`` (:meth:`check`) to the host without waiting, to be judged
        at the next step (the last one's step judged first)."""
        host = torch.empty(counts.shape, dtype=counts.dtype, pin_memory=True)
        host.copy_(counts, non_blocking=True)
        landed = torch.cuda.Event()
        landed.record()
        self.flush()
        self._pending = (host, landed, names, rows, measured, step)

    def flush(self) -> None:
        """Judge the step still queued, if any."""
        if self._pending is not None:
            host, landed, names, rows, measured, step = self._pending
            self._pending = None
            landed.synchronize()
            self._judge(host.tolist(), names, rows, measured, step)

    @staticmethod
    def _judge(counts: list[float], names: list[str], rows: list[int], measured: torch.Tensor, step: int) -> None:
        loss, bad = counts[0], [n - int(finite) for n, finite in zip(rows, counts[1:])]
        if math.isfinite(loss) and not any(bad):
            return
        cause = ", ".join(f"{v} Gaussian(s) with non-finite {k}" for k, v in zip(names, bad) if v) or (
            "the measured projection holds NaN/Inf"
            if not bool(torch.isfinite(measured).all())
            else "the projection overflowed (amplitudes too large for float32?)"
        )
        raise FloatingPointError(
            f"gaussian-atoms: step {step}: the loss is {loss} and training cannot go on; cause: {cause}. Lower the "
            f"learning rates or check the input."
        )
