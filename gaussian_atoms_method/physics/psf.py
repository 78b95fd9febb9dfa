"""The microscope's point-spread function, learned from the tilt series and shared by its views.

A probe is not a Gaussian: an aberrated STEM probe has a sharp core with rings and tails, a
ptychographic phase image rings at the transfer's edge.  Folded into every atom's width, the
core is harmless (an isotropic Gaussian atom blurred by a Gaussian is a wider Gaussian), but the
tails and rings are not Gaussian at all, and a fit without them explains them with extra, faint,
wide Gaussians.  So the projection is convolved with a radially symmetric kernel of unit
integral (mass is conserved)

    K = (1 - sum_k w_k) delta + sum_k w_k G(s_k),     K^(f) = 1 + sum_k w_k (exp(-2 pi^2 s_k^2 f^2) - 1)

over a ladder of widths :data:`KERNEL_WIDTHS_A`, with weights ``w_k`` learned with the atoms and
kept non-negative with the delta's share ``1 - sum w`` (:func:`project_weights` after every
step), so the kernel is a non-negative intensity, as an incoherent (ADF-STEM) probe's is, and
starts as the identity: a run whose data want no kernel renders exactly as without one.
Unconstrained weights on the Ta film went to -1.4 at 1 Å: a sharpening kernel that let the fit
put more, not fewer, Gaussians (0.71 extra atoms per model atom against 0.56).  Below the ladder the kernel
and the atoms' widths are one and the same thing (a narrower blur widens every atom alike), so
the kernel starts where an atom ends and an atom's width still holds its own share of the blur.
Applied by FFT on the zero-padded image (on a GPU, images up to :data:`MATRIX_BLUR_MAX_SIDE_PX`
by separable matrices: no cuFFT).  Pure torch.
"""

from __future__ import annotations

import functools
import math

import torch

KERNEL_WIDTHS_A = (1.0, 2.0, 4.0)
"""The kernel's Gaussian widths, Å: from about the widest atom (a blurred atom is 0.5-0.9 Å
wide; ``max_atom_sigma_A`` 1.5) to the few Å an aberrated probe's tails and rings reach (the
harness's 20 mrad probe at 40 Å defocus holds 9% of its intensity beyond 2 Å and 2% beyond 5)."""


KERNEL_MARGIN_WIDTHS = 3.0
"""Where matter lies beyond the detector (a film), each view is projected on a detector widened
by this many of the kernel's narrowest width (:data:`KERNEL_WIDTHS_A`, 1 Å) on
every side, blurred there and cut back: a probe's tails carry the image of what lies just
beyond the field into it, and a kernel applied to the detector alone leaves that out.  Measured
on a replica of Ta sub-area 21 (abTEM potentials, ADF contrast, the harness's aberrated probe,
white noise; the true atoms drawn through one Gaussian and the 1, 2, 4 Å kernel, weights fitted):
the misfit within 12 pixels of the detector's edge was 9.8 times the noise with no margin, 3.0
with 1 Å, 1.0 with 2 Å and 0.9 with 3 Å, and with no margin the fitted kernel lost its 4 Å share
(0 against 0.015).  Three widths hold a Gaussian's image to 1% of its peak."""


def kernel_margin_of(narrowest_width: float, pitch: float) -> int:
    """Pixels (of ``pitch``, in ``narrowest_width``'s length unit) each side of a view is widened by
    before the kernel: :data:`KERNEL_MARGIN_WIDTHS` of its narrowest width, rounded up.

    >>> kernel_margin_of(1.0, 0.4)
    8
    """
    return int(math.ceil(KERNEL_MARGIN_WIDTHS * narrowest_width / abs(pitch) - 1e-9))


def widened(coordinates: torch.Tensor, margin: int, pitch: float) -> torch.Tensor:
    """(n + 2 margin,) evenly spaced pixel coordinates: ``coordinates`` (n,) with ``margin`` more
    of spacing ``pitch`` before and after.

    >>> widened(torch.tensor([0.0, 1.0, 2.0]), 2, 1.0).tolist()
    [-2.0, -1.0, 0.0, 1.0, 2.0, 3.0, 4.0]
    """
    steps = torch.arange(1, margin + 1, device=coordinates.device, dtype=coordinates.dtype) * pitch
    return torch.cat([coordinates[0] - steps.flip(0), coordinates, coordinates[-1] + steps])


MATRIX_BLUR_MAX_SIDE_PX = 320
"""The largest image side (px) a GPU blurs by matrices (:func:`apply_kernel_by_matrices`), not
by FFT.  The products' work grows as the side cubed, the FFT's barely; at this side a
3,000-step run's extra time in products equals what the matrices spare it, cuFFT's first use in
the process (``scripts/studies/psf_blur_cost.py`` measures both)."""


@torch.no_grad()
def project_weights(weights: torch.Tensor) -> None:
    """In place: every weight at least 0 and their sum at most 1 (a non-negative kernel).  A
    projected gradient step: a weight pushed below zero comes back to zero, where the data can
    still lift it."""
    weights.clamp_(min=0.0)
    weights.div_(weights.sum().clamp(min=1.0))  # on the device: no host round-trip per step


def kernel_transfer(freq2: torch.Tensor, widths: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """``K^(f) = 1 + sum_k w_k (exp(-2 pi^2 s_k^2 f^2) - 1)`` at squared spatial frequencies
    ``freq2`` (any shape, 1 / length^2), for widths (K,) (length) and weights (K,)."""
    gauss = torch.exp(-2.0 * math.pi**2 * widths.to(freq2) ** 2 * freq2[..., None])
    return 1.0 + ((gauss - 1.0) * weights.to(freq2)).sum(dim=-1)


def fast_fft_length(n: int) -> int:
    """The smallest ``2^a 3^b`` at least ``n``: an FFT length both pocketfft (torch's CPU) and
    cuFFT transform fast (a prime length is several times slower than the next such length)."""
    best, power2 = 1 << max(int(n) - 1, 0).bit_length(), 1
    while power2 < best:
        m = power2
        while m < n:
            m *= 3
        best, power2 = min(best, m), power2 * 2
    return best


def _squared_frequencies(ph: int, pw: int, spacing: float, device, dtype) -> torch.Tensor:
    """(ph, pw // 2 + 1) squared spatial frequencies of ``rfft2`` on a ph x pw grid of pitch ``spacing``."""
    fy = torch.fft.fftfreq(ph, d=spacing, device=device, dtype=dtype)
    fx = torch.fft.rfftfreq(pw, d=spacing, device=device, dtype=dtype)
    return fy[:, None] ** 2 + fx[None, :] ** 2


@functools.lru_cache(maxsize=16)
def _gaussian_factors(
    ph: int, pw: int, spacing: float, widths: tuple[float, ...], device: torch.device, dtype: torch.dtype
) -> torch.Tensor:
    """(ph, pw // 2 + 1, K) ``exp(-2 pi^2 s_k^2 f^2) - 1`` on the ``rfft2`` grid: fixed for a run's
    image grid, so computed once (the transfer is then one product with the weights)."""
    freq2 = _squared_frequencies(ph, pw, spacing, device, dtype)
    return torch.expm1(-2.0 * math.pi**2 * torch.tensor(widths, device=device, dtype=dtype) ** 2 * freq2[..., None])


def apply_kernel(
    images: torch.Tensor, spacing: float, widths: torch.Tensor | tuple[float, ...], weights: torch.Tensor
) -> torch.Tensor:
    """(..., H, W) images convolved with the kernel (pixel ``spacing`` in the widths' unit),
    zero-padded by at least three of the widest width so nothing wraps around (to a fast FFT
    length, :func:`fast_fft_length`); same shape.  All weights
    zero and no gradient wanted for them: the images themselves (no transform).  On a GPU, images
    up to :data:`MATRIX_BLUR_MAX_SIDE_PX` are blurred by :func:`apply_kernel_by_matrices`.

    ``widths``: (K,) a tensor, or a tuple of floats already on the host (a training step's: the
    transfer's Gaussian factors are then kept per image grid, :func:`_gaussian_factors`, and
    nothing is read from a GPU)."""
    if not (weights.requires_grad and torch.is_grad_enabled()) and not bool((weights != 0).any()):
        return images
    if images.is_cuda and max(images.shape[-2:]) <= MATRIX_BLUR_MAX_SIDE_PX:
        return apply_kernel_by_matrices(images, spacing, widths, weights)
    return apply_kernel_by_fft(images, spacing, widths, weights)


def apply_kernel_by_fft(
    images: torch.Tensor, spacing: float, widths: torch.Tensor | tuple[float, ...], weights: torch.Tensor
) -> torch.Tensor:
    """:func:`apply_kernel` by FFT, always (the host's way, and a GPU's for large images)."""
    h, w = images.shape[-2:]
    widest = (max(widths) if isinstance(widths, tuple) else float(widths.max())) if len(widths) else 0.0
    pad = int(math.ceil(3.0 * widest / spacing))
    ph, pw = fast_fft_length(h + 2 * pad), fast_fft_length(w + 2 * pad)  # the extra zeros after the image
    if isinstance(widths, tuple):
        transfer = 1.0 + _gaussian_factors(ph, pw, float(spacing), widths, images.device, images.dtype) @ weights.to(
            images.dtype
        )
    else:
        transfer = kernel_transfer(_squared_frequencies(ph, pw, spacing, images.device, images.dtype), widths, weights)
    spectrum = torch.fft.rfft2(torch.nn.functional.pad(images, (pad, pw - w - pad, pad, ph - h - pad)))
    return torch.fft.irfft2(spectrum * transfer, s=(ph, pw))[..., pad : pad + h, pad : pad + w]


@functools.lru_cache(maxsize=16)
def _gaussian_matrices(n: int, spacing: float, widths: tuple[float, ...], device: torch.device, dtype) -> torch.Tensor:
    """(K, n, n) symmetric matrices of a sampled unit-integral Gaussian of each width along one
    image axis, ``spacing / (sqrt(2 pi) s) exp(-(i - j)^2 spacing^2 / (2 s^2))``: one axis of
    a blur by ``G(s)``, untruncated and with zeros beyond the image, as the zero-padded FFT's."""
    offsets = torch.arange(n, dtype=torch.float64)
    distance2 = ((offsets[:, None] - offsets[None, :]) * spacing) ** 2
    s = torch.tensor(widths, dtype=torch.float64)[:, None, None]
    return (spacing / (math.sqrt(2 * math.pi) * s) * torch.exp(-distance2 / (2 * s**2))).to(device, dtype)


def apply_kernel_by_matrices(
    images: torch.Tensor, spacing: float, widths: torch.Tensor | tuple[float, ...], weights: torch.Tensor
) -> torch.Tensor:
    """:func:`apply_kernel` by matrix products, a GPU's way: every kernel Gaussian is separable,
    so ``G_k * X = A_k X B_k`` with :func:`_gaussian_matrices` along the rows and the columns.
    No FFT: cuFFT's first use in a process costs a GPU run a quarter of a second or more, and
    every run applies the kernel from its first step.  The FFT's images and gradients to 1e-9 of
    the peak: what differs is the FFT's own aliasing, ``exp(-pi^2 s^2 / (2 spacing^2))``, about
    3e-9 at a width of two pixels (``tests/test_psf.py``)."""
    widths = tuple(float(x) for x in (widths if isinstance(widths, tuple) else widths.tolist()))
    if not widths:
        return images
    h, w = images.shape[-2:]
    k = len(widths)
    rows = _gaussian_matrices(h, float(spacing), widths, images.device, images.dtype)  # (K, H, H)
    cols = _gaussian_matrices(w, float(spacing), widths, images.device, images.dtype)  # (K, W, W)
    along_cols = (images @ cols.permute(1, 0, 2).reshape(w, k * w)).unflatten(-1, (k, w)).transpose(-3, -2)
    blurred = rows @ along_cols  # (..., K, H, W)
    weights = weights.to(images.dtype)
    return images * (1.0 - weights.sum()) + (blurred * weights[:, None, None]).sum(dim=-3)


def fit_kernel_weights(
    images: torch.Tensor,
    background: torch.Tensor,
    measured: torch.Tensor,
    spacing: float,
    widths: torch.Tensor,
    loss,
    iterations: int = 20,
) -> torch.Tensor:
    """(K,) the kernel's weights that best carry (V, H, W) kernel-free projections ``images``
    plus their ``background`` (broadcastable) onto the ``measured`` views, under ``loss``
    (a callable (predicted, measured) -> scalar, the run's data term).

    The blurred image is linear in the weights, ``images + sum_k w_k (G_k * images - images)``,
    and every data term here is convex in the prediction, so projected Newton steps (the
    weights at zero held there while the gradient pushes them below; halved until the loss
    falls; then :func:`project_weights`) reach the constrained optimum in a few iterations.  Used
    on views the atoms were not fitted to (``psf held-out``)."""
    one = torch.ones(1, dtype=images.dtype, device=images.device)
    basis = torch.stack(
        [apply_kernel(images, spacing, widths[k : k + 1], one) - images for k in range(len(widths))], dim=-1
    )
    base = images + background

    def objective(w: torch.Tensor) -> torch.Tensor:
        return loss(base + basis @ w, measured)

    weights = torch.zeros(len(widths), dtype=images.dtype, device=images.device)
    with torch.enable_grad():
        for _ in range(iterations):
            w = weights.clone().requires_grad_(True)
            value = objective(w)
            (grad,) = torch.autograd.grad(value, w, create_graph=True)
            hess = torch.stack([torch.autograd.grad(grad[k], w, retain_graph=True)[0] for k in range(len(w))]).detach()
            grad, value = grad.detach(), value.detach()
            free = ~((weights <= 0) & (grad > 0))
            step = torch.zeros_like(weights)
            if bool(free.any()):
                h = hess[free][:, free] + 1e-12 * torch.eye(
                    int(free.sum()), dtype=hess.dtype, device=hess.device
                ) * hess.diagonal().abs().max().clamp_min(1e-30)
                step[free] = -torch.linalg.solve(h, grad[free])
            moved = False
            for _ in range(30):  # backtracking: a Huber or Poisson term is not one quadratic
                trial = weights + step
                project_weights(trial)
                with torch.no_grad():
                    if float(objective(trial)) <= float(value):
                        moved = not torch.equal(trial, weights)
                        weights = trial
                        break
                step = step / 2
            if not moved or float((step.abs()).max()) < 1e-5:
                break
    return weights
