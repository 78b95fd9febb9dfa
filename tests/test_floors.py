"""The views' floors in closed form (gaussian_atoms_method.engine.floors)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import torch

from gaussian_atoms_method.engine.floors import FloorSolver, agree, floor_moments
from gaussian_atoms_method.engine.rendering import (
    FLOOR_TERMS,
    add_background,
    coordinate_powers,
    floor_images,
)
from gaussian_atoms_method.physics.noise import NoiseModel


def _model(coefficients: np.ndarray, read_var: float, surfaces: int = 0) -> SimpleNamespace:
    return SimpleNamespace(
        training=True,
        rendered_floors=None,
        step=0,
        noise_read=NoiseModel(read_var, 0.0),
        config=SimpleNamespace(refine_every=10),
        view_params={
            "background": torch.nn.Parameter(torch.as_tensor(coefficients, dtype=torch.float32), requires_grad=False)
        },
        background_surfaces=torch.zeros(surfaces, 40, 48),
    )


def _views(true: np.ndarray, noise_std: float, seed: int = 0):
    """(V, H, W, 1) float64 measured views: a blob (the object) on each view's floor ``true`` (V, K), plus noise; and
    the rows and columns."""
    rows, cols = torch.linspace(-0.5, 0.5, 40, dtype=torch.float64), torch.linspace(-0.6, 0.6, 48, dtype=torch.float64)
    blob = 50.0 * torch.exp(-(rows[:, None] ** 2 + cols[None, :] ** 2) / 0.02)
    rng = np.random.default_rng(seed)
    views = [
        add_background(blob, torch.as_tensor(c), rows, cols) + torch.as_tensor(rng.normal(0.0, noise_std, blob.shape))
        for c in true
    ]
    return torch.stack(views)[..., None], blob, rows, cols


def _fit(model, measured, blob, rows, cols, per_step: int = 1) -> None:
    """One interval: every view rendered once (the object exact, the floors as they stand), then solved."""
    coefficients = model.view_params["background"]
    for start in range(0, len(measured), per_step):
        views = list(range(start, min(start + per_step, len(measured))))
        powers = coordinate_powers(rows, cols)
        floors = floor_images(coefficients.data[views].double(), powers)
        model.rendered_floors = (views, powers, floors)
        model.floors.accumulate(model, (blob + floors)[..., None], measured[views])
    model.floors.decide(model, 10)


def test_each_views_floor_is_its_least_squares_fit():
    """Floors that differ between the views (a plane each, 5% of the object's peak) from a start at
    zero: one interval's solve gives each view its least-squares plane under the object, to four
    standard errors of a constant over the view's 1,920 pixels (noise 1: 0.023 x 4 = 0.09); more
    views a step give the same fit."""
    rng = np.random.default_rng(1)
    true = np.stack([rng.uniform(2.0, 5.0, 6), rng.uniform(-1, 1, 6), rng.uniform(-1, 1, 6)], axis=1)
    measured, blob, rows, cols = _views(true, 1.0)
    results = []
    for per_step in (1, 3):
        model = _model(np.zeros((6, 3)), 1.0)
        model.floors = FloorSolver()
        _fit(model, measured, blob, rows, cols, per_step)
        assert model.floors.shared is False
        results.append(model.view_params["background"].data.double().numpy())
    np.testing.assert_allclose(results[0][:, 0], true[:, 0], atol=4 / math.sqrt(40 * 48))
    np.testing.assert_allclose(results[0], results[1], rtol=0, atol=1e-5)
    # Noise-free, the fit is exact (float32 coefficients).
    model = _model(np.zeros((6, 3)), 1.0)
    model.floors = FloorSolver()
    _fit(model, _views(true, 0.0)[0], blob, rows, cols)
    np.testing.assert_allclose(model.view_params["background"].data.double().numpy(), true, rtol=0, atol=1e-4)


def test_floors_that_agree_are_one_floor_fitted_to_every_view():
    """One constant floor under 20 views (a detector offset): their fits agree within the noise,
    so every view gets the fit to all of them, four standard errors of the pooled mean (noise 2
    over 20 x 1,920 pixels: 0.010 x 4); a view not rendered in the interval gets it too.  A fixed
    per-view surface (a smooth floor) keeps the views apart."""
    true = np.full((20, 1), 3.0)
    measured, blob, rows, cols = _views(true, 2.0, seed=3)
    model = _model(np.zeros((21, 1)), 4.0)
    model.floors = FloorSolver()
    _fit(model, measured, blob, rows, cols)
    fitted = model.view_params["background"].data.double().numpy()[:, 0]
    assert model.floors.shared is True
    np.testing.assert_allclose(fitted, fitted[0], rtol=0, atol=0)
    assert abs(fitted[0] - 3.0) < 4 * 2.0 / math.sqrt(20 * 40 * 48)
    model = _model(np.zeros((20, 1)), 4.0, surfaces=20)
    model.floors = FloorSolver()
    _fit(model, measured, blob, rows, cols)
    assert model.floors.shared is False


def test_agree_is_a_chi_square_test_in_units_of_the_noise():
    """Values scattered by exactly their standard errors agree; five times that does not."""
    rng = np.random.default_rng(0)
    gram = torch.eye(2, dtype=torch.float64).expand(400, 2, 2) * 4.0  # standard error 0.5
    scatter = torch.as_tensor(rng.normal(0.0, 0.5, (400, 2)))
    shared, pooled = agree(1.0 + scatter, gram)
    assert shared and torch.allclose(pooled, 1.0 + scatter.mean(0))
    assert not agree(1.0 + 5.0 * scatter, gram)[0]
    assert not agree(torch.ones(1, 2, dtype=torch.float64), gram[:1])[0]  # one view: nothing to pool


def test_the_floor_terms_are_add_backgrounds_and_their_moments_the_pixel_sums():
    """Each coefficient of :func:`add_background` multiplies the powers FLOOR_TERMS names, and
    floor_moments equals the pixel sums it stands for (float64)."""
    rows, cols = torch.linspace(-0.4, 0.5, 7, dtype=torch.float64), torch.linspace(-0.6, 0.3, 9, dtype=torch.float64)
    for k, (a, b) in enumerate(FLOOR_TERMS):
        unit = torch.zeros(6, dtype=torch.float64)
        unit[k] = 1.0
        torch.testing.assert_close(
            add_background(torch.zeros(7, 9, dtype=torch.float64), unit, rows, cols),
            rows[:, None] ** a * cols[None, :] ** b,
            rtol=0,
            atol=1e-15,
        )
    weights = torch.as_tensor(np.random.default_rng(2).uniform(0, 1, (2, 7, 9)))
    moments = floor_moments(weights, *coordinate_powers(rows, cols))
    for a in range(5):
        for b in range(5):
            torch.testing.assert_close(
                moments[:, a, b],
                (weights * rows[:, None] ** a * cols[None, :] ** b).sum(dim=(1, 2)),
                rtol=1e-12,
                atol=1e-15,
            )


def test_a_view_the_object_fills_keeps_its_floor():
    """Where the Gaussians put more than OBJECT_FREE noise deviations on every pixel (a film
    wider than the field of view) the view's floor is not identified apart from the object: it
    keeps its value, finite."""
    rows, cols = torch.linspace(-0.5, 0.5, 40, dtype=torch.float64), torch.linspace(-0.6, 0.6, 48, dtype=torch.float64)
    model = _model(np.array([[2.5]]), 1.0)
    model.floors = FloorSolver()
    film = torch.full((1, 40, 48, 1), 30.0, dtype=torch.float64)
    model.rendered_floors = ([0], coordinate_powers(rows, cols), torch.full((1, 40, 48), 2.5, dtype=torch.float64))
    model.floors.accumulate(model, film + 2.5, film + 4.0)
    assert model.view_params["background"].data[0, 0].item() == 2.5
