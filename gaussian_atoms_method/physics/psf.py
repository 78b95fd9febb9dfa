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
Applied by FFT on the zero-padded image.  Pure torch.
"""

from __future__ import annotations

import math

import torch

KERNEL_WIDTHS_A = (1.0, 2.0, 4.0)
"""The kernel's Gaussian widths, Å: from about the widest atom (a blurred atom is 0.5-0.9 Å
wide; ``max_atom_sigma_A`` 1.5) to the few Å an aberrated probe's tails and rings reach (the
harness's 20 mrad probe at 40 Å defocus holds 9% of its intensity beyond 2 Å and 2% beyond 5)."""


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


def apply_kernel(images: torch.Tensor, spacing: float, widths: torch.Tensor, weights: torch.Tensor, widest: float | None = None) -> torch.Tensor:
    """(..., H, W) images convolved with the kernel (pixel ``spacing`` in the widths' unit),
    zero-padded by three of the widest width so nothing wraps around; same shape.  All weights
    zero and no gradient wanted for them: the images themselves (no transform).  ``widest``:
    ``widths.max()`` if already known (reading it from a GPU tensor waits for the GPU)."""
    if not (weights.requires_grad and torch.is_grad_enabled()) and not bool((weights != 0).any()):
        return images
    h, w = images.shape[-2:]
    widest = float(widths.max()) if widest is None and len(widths) else widest
    pad = int(math.ceil(3.0 * widest / spacing)) if len(widths) else 0
    ph, pw = h + 2 * pad, w + 2 * pad
    fy = torch.fft.fftfreq(ph, d=spacing, device=images.device, dtype=images.dtype)
    fx = torch.fft.rfftfreq(pw, d=spacing, device=images.device, dtype=images.dtype)
    transfer = kernel_transfer(fy[:, None] ** 2 + fx[None, :] ** 2, widths, weights)
    spectrum = torch.fft.rfft2(torch.nn.functional.pad(images, (pad, pad, pad, pad)))
    return torch.fft.irfft2(spectrum * transfer, s=(ph, pw))[..., pad : pad + h, pad : pad + w]


def fit_kernel_weights(images: torch.Tensor, background: torch.Tensor, measured: torch.Tensor, spacing: float, widths: torch.Tensor,
                       loss, iterations: int = 20) -> torch.Tensor:  # fmt: skip
    """(K,) the kernel's weights that best carry (V, H, W) kernel-free projections ``images``
    plus their ``background`` (broadcastable) onto the ``measured`` views, under ``loss``
    (a callable (predicted, measured) -> scalar, the run's data term).

    The blurred image is linear in the weights, ``images + sum_k w_k (G_k * images - images)``,
    and every data term here is convex in the prediction, so projected Newton steps (the
    weights at zero held there while the gradient pushes them below; halved until the loss
    falls; then :func:`project_weights`) reach the constrained optimum in a few iterations.  Used
    on views the atoms were not fitted to (``psf held-out``)."""
    one = torch.ones(1, dtype=images.dtype, device=images.device)
    basis = torch.stack([apply_kernel(images, spacing, widths[k : k + 1], one) - images for k in range(len(widths))], dim=-1)
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
                h = hess[free][:, free] + 1e-12 * torch.eye(int(free.sum()), dtype=hess.dtype, device=hess.device) * hess.diagonal().abs().max().clamp_min(1e-30)
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
