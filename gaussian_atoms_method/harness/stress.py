"""Numerical stress cases for the projector, the merge and training (``gaussian-atoms stress``).

Each case returns ``(name, passed, detail)``.  The tolerances are those float32 arithmetic can
meet: values within 1e-5 of the image peak of the float64 result (float32 has 6e-8 relative
resolution; sums of thousands of terms and exponentials of large arguments lose about two
orders), gradients within 1e-3 of their largest magnitude.
"""

from __future__ import annotations

import math
import resource
import time
from typing import Callable

import numpy as np
import torch

from gaussian_atoms_method.atoms.merge import cluster_labels, merged_values
from gaussian_atoms_method.physics.geometry import detector_axes_from_tilts
from gaussian_atoms_method.physics.projector import gaussian_mass, project_gaussians, project_gaussians_tiled

Case = tuple[str, bool, str]


def _scene(n: int, sigma_px: tuple[float, float], amp: tuple[float, float], spread: float, seed: int, pixels: int = 96):
    g = torch.Generator().manual_seed(seed)
    px = 1.0 / pixels
    means = (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * spread
    sig = px * sigma_px[0] * (sigma_px[1] / sigma_px[0]) ** torch.rand(n, generator=g, dtype=torch.float64)
    amps = amp[0] * (amp[1] / amp[0]) ** torch.rand(n, generator=g, dtype=torch.float64)
    axes = torch.tensor(detector_axes_from_tilts(np.array([-70.0, 0.0, 45.0]), "y"))
    coords = (torch.arange(pixels, dtype=torch.float64) + 0.5 - pixels / 2) * px
    return means, sig, amps, axes, coords


def _value_and_grads(project: Callable, means, sig, amps, axes, coords, dtype):
    params = [t.to(dtype).clone().requires_grad_() for t in (means, sig, amps)]
    img = project(*params, axes.to(dtype), coords.to(dtype), coords.to(dtype))
    weights = torch.linspace(0.5, 1.5, img.numel(), dtype=dtype).reshape(img.shape)
    (img * weights).sum().backward()
    return img.detach().double(), [p.grad.double() for p in params]


def precision_case(name: str, sigma_px, amp, spread: float = 0.6, n: int = 300) -> Case:
    """float32 against float64, for the dense and the tiled projector."""
    scene = _scene(n, sigma_px, amp, spread, seed=len(name))
    worst_v, worst_g, finite = 0.0, 0.0, True
    ref, ref_grads = _value_and_grads(project_gaussians, *scene, torch.float64)
    for project in (project_gaussians, project_gaussians_tiled):
        img, grads = _value_and_grads(project, *scene, torch.float32)
        finite &= bool(torch.isfinite(img).all()) and all(bool(torch.isfinite(g).all()) for g in grads)
        worst_v = max(worst_v, float((img - ref).abs().max() / ref.abs().max().clamp_min(1e-300)))
        for g, r in zip(grads, ref_grads):
            worst_g = max(worst_g, float((g - r).abs().max() / r.abs().max().clamp_min(1e-300)))
    ok = finite and worst_v <= 1e-5 and worst_g <= 1e-3
    return name, ok, f"float32 vs float64: values {worst_v:.1e} of peak, gradients {worst_g:.1e} of max"


def edge_case() -> Case:
    """Atoms on and beyond the detector edge: the tiled projector equals the exact one."""
    means, sig, amps, axes, coords = _scene(400, (0.5, 4.0), (0.1, 10.0), spread=1.6, seed=11)
    dense = project_gaussians(means, sig, amps, axes, coords, coords)
    tiled = project_gaussians_tiled(means, sig, amps, axes, coords, coords)
    err = float((dense - tiled).abs().max() / dense.abs().max())
    return "atoms on and beyond the edge", err <= 1e-6, f"tiled vs exact (float64): {err:.1e} of peak"


def coincident_case() -> Case:
    """Coincident Gaussians: projection and gradients finite; the merge folds them into one of
    the summed mass."""
    means = torch.zeros(5, 3, dtype=torch.float64)
    sig = torch.full((5,), 0.01, dtype=torch.float64)
    amps = torch.ones(5, dtype=torch.float64)
    _, _, _, axes, coords = _scene(1, (1, 2), (1, 2), 0.1, seed=0)
    img, grads = _value_and_grads(project_gaussians_tiled, means, sig, amps, axes, coords, torch.float32)
    labels, n_clusters = cluster_labels(means.numpy(), 1e-3)
    _, new_sig, new_amp = merged_values(means, sig, amps, torch.as_tensor(labels), n_clusters)
    mass_ok = math.isclose(
        float(gaussian_mass(new_sig, new_amp).sum()), float(gaussian_mass(sig, amps).sum()), rel_tol=1e-12
    )
    ok = (
        bool(torch.isfinite(img).all())
        and all(bool(torch.isfinite(g).all()) for g in grads)
        and n_clusters == 1
        and mass_ok
    )
    return (
        "coincident atoms",
        ok,
        f"finite projection and gradients; merged into {n_clusters} with mass conserved: {mass_ok}",
    )


def zero_projections_case() -> Case:
    """All-zero projections are refused with a clear message, not divided by zero."""
    from gaussian_atoms_method.physics.units import Normalisation

    try:
        Normalisation.for_tilt_series(np.zeros((3, 8, 8)), 0.25)
    except ValueError as exc:
        return "all-zero projections", "all zero" in str(exc), f"refused: {exc}"
    return "all-zero projections", False, "accepted: the normalisation would divide by zero"


def low_snr_case(steps: int = 150) -> Case:
    """SNR below 1: a short training on noise-dominated data stays finite and ends with a finite
    loss (nerfstudio layer, CPU)."""
    import tempfile
    from pathlib import Path

    from dataparsers.tilt_series_dataparser import TiltSeriesDataParserConfig
    from dataparsers.tilt_series_format import write_tilt_series
    from gaussian_atoms_method.harness.simulate import simulate_gaussian_tilt_series, spherical_particle
    from gaussian_atoms_method.nerfstudio_layer.launch import train_views
    from gaussian_atoms_method.nerfstudio_layer.model import GaussianAtomsModelConfig

    atoms = spherical_particle("Au", radius_A=5.0)
    angles = np.linspace(-60, 60, 13)
    clean = simulate_gaussian_tilt_series(atoms, angles, noise_std=0.0)
    noise_std = 2.0 * float(clean.projections.max())  # peak-to-noise 0.5
    sim = simulate_gaussian_tilt_series(atoms, angles, noise_std=noise_std, seed=3)
    with tempfile.TemporaryDirectory() as tmp:
        write_tilt_series(Path(tmp), sim.projections, angles, sim.pixel_size_A)
        outputs = TiltSeriesDataParserConfig(data=Path(tmp)).setup().get_dataparser_outputs("train")
        model = GaussianAtomsModelConfig(num_random=500, warmup_length=20, refine_every=20, merge_every=20).setup(
            scene_box=outputs.scene_box, num_train_data=len(angles), metadata=outputs.metadata
        )
        targets = [outputs.metadata["projections"][v][..., None] for v in range(len(angles))]
        loss = train_views(model, outputs.cameras, targets, steps)
    finite = all(bool(torch.isfinite(p).all()) for p in model.gauss_params.values())
    return (
        "SNR below 1 (peak-to-noise 0.5)",
        finite and math.isfinite(loss),
        f"{steps} steps: loss {loss:.3g}, {model.num_points} Gaussians, all finite: {finite}",
    )


def many_atoms_case(n: int = 100_000, pixels: int = 280) -> Case:
    """100k Gaussians on a 280 x 280 view: the tiled projector (float32, forward and backward)
    against the dense reference in float64; time and memory of the tiled one."""
    g = torch.Generator().manual_seed(0)
    means = (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * 0.8
    sig = torch.full((n,), 0.6 / 70, dtype=torch.float64)
    amps = 10.0 ** (torch.rand(n, generator=g, dtype=torch.float64) - 0.5)  # a factor 10 in amplitude
    axes = torch.tensor(detector_axes_from_tilts(np.array([30.0]), "y"))
    coords = (torch.arange(pixels, dtype=torch.float64) + 0.5 - pixels / 2) / pixels
    start = time.perf_counter()
    img, grads = _value_and_grads(project_gaussians_tiled, means, sig, amps, axes, coords, torch.float32)
    seconds = time.perf_counter() - start
    rss_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    ref, ref_grads = _value_and_grads(project_gaussians, means, sig, amps, axes, coords, torch.float64)
    value_err = float((img - ref).abs().max() / ref.abs().max())
    grad_err = max(float((g - r).abs().max() / r.abs().max()) for g, r in zip(grads, ref_grads))
    ok = bool(torch.isfinite(img).all()) and value_err <= 1e-5 and grad_err <= 1e-3
    return (
        f"{n:,} atoms",
        ok,
        f"tiled float32 vs dense float64: values {value_err:.1e} of peak, gradients {grad_err:.1e} of max; "
        f"forward+backward of one {pixels}x{pixels} view in {seconds:.2f} s; peak RSS {rss_gb:.1f} GB",
    )


CASES: dict[str, tuple[Callable[[], Case], bool]] = {
    # name: (case, slow)
    "sigma 0.05-0.5 px": (lambda: precision_case("sigma 0.05-0.5 px", (0.05, 0.5), (1.0, 10.0)), False),
    "sigma 2-20 px": (lambda: precision_case("sigma 2-20 px", (2.0, 20.0), (1.0, 10.0), n=60), False),
    "amplitudes 1e-3-1e3": (lambda: precision_case("amplitudes 1e-3-1e3", (0.5, 4.0), (1e-3, 1e3)), False),
    "edge": (edge_case, False),
    "coincident": (coincident_case, False),
    "all-zero projections": (zero_projections_case, False),
    "SNR below 1": (low_snr_case, True),
    "100k atoms": (many_atoms_case, True),
}
"""Every stress case by name; ``slow``: training or 100k atoms (seconds, not milliseconds)."""


def run_stress(include_slow: bool = True) -> list[Case]:
    """Run the cases (``include_slow=False`` leaves out the slow ones)."""
    return [case() for case, slow in CASES.values() if include_slow or not slow]
