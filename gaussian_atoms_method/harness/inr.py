"""Implicit neural representation baseline: a coordinate MLP fitted to the projections.

The potential is an MLP of position (random Fourier features, softplus output so the density
is non-negative), times ``density_scale``.  It is trained with the same projection geometry as our method
(:mod:`gaussian_atoms_method.physics.geometry`, normalised units of :mod:`gaussian_atoms_method.physics.units`): a
batch of detector pixels of one view,
each ray's line integral estimated by stratified samples along the beam, L1 loss against the
measured values.  Afterwards the MLP is sampled on the voxel grid and traced like FBP/SART.

The defaults are tuned (``scripts/studies/inr_tune.py``; docs/results.md, INR baseline): a small
MLP cannot hold hundreds of sharp peaks, a short run does not pass over every pixel, and a raw
softplus output has to grow to an atom's peak density through small Adam steps; so the
defaults have four times the hidden units of a first try, a density scale, 10,000 steps of
8,192 rays and Fourier features of 0.35 cycles/Å, which find every atom of the Au particle.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from gaussian_atoms_method.physics.geometry import detector_axes_from_tilts, pixel_centres
from gaussian_atoms_method.physics.reconstruction import Volume
from gaussian_atoms_method.physics.units import Normalisation


class CoordinateMLP(torch.nn.Module):
    """``f(r) >= 0`` for normalised positions ``r`` (M, 3) in [-0.5, 0.5]^3."""

    def __init__(
        self, n_frequencies: int = 64, frequency_std: float = 20.0, hidden: int = 64, layers: int = 3, seed: int = 0
    ):
        super().__init__()
        gen = torch.Generator().manual_seed(seed)
        self.register_buffer("frequencies", torch.randn(3, n_frequencies, generator=gen) * frequency_std)
        dims = [2 * n_frequencies] + [hidden] * layers
        blocks = []
        for a, b in zip(dims[:-1], dims[1:]):
            blocks += [torch.nn.Linear(a, b), torch.nn.ReLU()]
        self.body = torch.nn.Sequential(*blocks, torch.nn.Linear(hidden, 1))

    def forward(self, r: torch.Tensor) -> torch.Tensor:
        phase = 2 * math.pi * r @ self.frequencies
        return torch.nn.functional.softplus(self.body(torch.cat([torch.sin(phase), torch.cos(phase)], dim=-1))).squeeze(
            -1
        )


def fit_inr(
    projections: np.ndarray,
    angles_deg: np.ndarray,
    pixel_size_A: float,
    tilt_axis: str = "y",
    centre_px=None,
    steps: int = 10000,
    rays_per_step: int = 8192,
    samples_per_ray: int = 64,
    learning_rate: float = 2e-3,
    seed: int = 0,
    device: str = "cpu",
    frequency_std_per_A: float = 0.35,
    hidden: int = 256,
    tilt_axis_angle_deg: float = 0.0,
    density_scale: float = 100.0,
    layers: int = 3,
) -> Volume:
    """Fit an INR to a tilt series and sample it on the voxel grid (values per Å, like FBP).

    ``frequency_std_per_A``: standard deviation of the random Fourier frequencies, cycles per
    Å (0.35: a blurred atom of sigma 0.6 Å has its spectrum within about 1 / (2 pi 0.6 Å) =
    0.27 cycles/Å; 10 per normalised unit on the 29 Å detector where it was tuned).
    ``density_scale`` multiplies the MLP's output (normalised units: an atom's peak density is
    thousands, so the MLP's own output stays near tens).  A GPU is needed for the defaults
    (10,000 steps of 8,192 rays of 64 samples each).

    Returns
    -------
    Volume with ``data[x, y, z]`` of side ``max(H, W)``, voxel size ``pixel_size_A``, the tilt
    centre at the middle.
    """
    projections = np.asarray(projections, dtype=np.float32)
    n_views, h, w = projections.shape
    norm = Normalisation.for_tilt_series(projections, pixel_size_A)
    ci, cj = ((h - 1) / 2, (w - 1) / 2) if centre_px is None else centre_px
    px = pixel_size_A * norm.length_scale
    frequency_std = frequency_std_per_A / norm.length_scale  # cycles per normalised unit
    rows = torch.tensor(pixel_centres(h, px, ci), dtype=torch.float32, device=device)
    cols = torch.tensor(pixel_centres(w, px, cj), dtype=torch.float32, device=device)
    axes = torch.tensor(
        detector_axes_from_tilts(angles_deg, tilt_axis, tilt_axis_angle_deg), dtype=torch.float32, device=device
    )
    target = torch.from_numpy(projections * np.float32(norm.data_scale)).to(device)
    with torch.random.fork_rng(devices=[]):  # the layers' initial weights from ``seed``; the caller's generator kept
        torch.manual_seed(seed)
        model = CoordinateMLP(frequency_std=frequency_std, hidden=hidden, layers=layers, seed=seed).to(device)
    opt = torch.optim.Adam(model.parameters(), lr=learning_rate)
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma=0.1 ** (1.0 / max(1, steps)))
    gen = torch.Generator(device="cpu").manual_seed(seed)
    half_depth = 0.5 * math.sqrt(2.0)  # a ray through the [-0.5, 0.5]^2 slab at any tilt
    for _ in range(steps):
        v = int(torch.randint(n_views, (1,), generator=gen))
        pix = torch.randint(h * w, (rays_per_step,), generator=gen).to(device)
        i, j = pix // w, pix % w
        start = rows[i, None] * axes[v, 0] + cols[j, None] * axes[v, 1]  # (R, 3)
        # Stratified samples along the beam: an unbiased estimate of the line integral.
        t = (
            torch.arange(samples_per_ray, device=device)
            + torch.rand(rays_per_step, samples_per_ray, generator=gen).to(device)
        ) / samples_per_ray
        t = (2 * t - 1) * half_depth
        points = start[:, None, :] + t[..., None] * axes[v, 2]
        inside = (points.abs() <= 0.5).all(-1)
        density = density_scale * model(points.reshape(-1, 3)).reshape(rays_per_step, samples_per_ray) * inside
        pred = density.sum(-1) * (2 * half_depth / samples_per_ray)
        loss = torch.abs(pred - target[v, i, j]).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
    side = max(h, w)
    grid = torch.tensor(pixel_centres(side, px), dtype=torch.float32, device=device)
    out = np.empty((side, side, side), dtype=np.float32)
    with torch.no_grad():
        yy, zz = torch.meshgrid(grid, grid, indexing="ij")
        for a in range(side):  # one x-plane at a time bounds the memory
            pts = torch.stack([torch.full_like(yy, float(grid[a])), yy, zz], -1).reshape(-1, 3)
            out[a] = (density_scale * model(pts)).reshape(side, side).cpu().numpy()
    # Normalised density -> values per Å (input units per Å), as the other baselines.
    out *= norm.length_scale / norm.data_scale
    return Volume(out, float(pixel_size_A), np.full(3, (side - 1) / 2.0))
