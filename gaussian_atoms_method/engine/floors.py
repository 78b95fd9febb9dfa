"""The views' floors (the background under the atoms), solved in closed form.

A floor's coefficients (:func:`.rendering.add_background`: a constant, a plane or a quadratic
surface per view) enter the projections linearly, so with the Gaussians held their best values
are a weighted least-squares fit of the residual: the Gauss-Newton step of the data term, each
pixel weighted by one over the noise variance at its predicted level, over the pixels the
Gaussians leave empty (:func:`background_weights`).  Each time a view is rendered its normal
equations replace its last ones and its floor moves to their fit (:meth:`FloorSolver.accumulate`).
Learned by Adam instead, a view's floor moved only on the steps that rendered it (1 in 47 on a
47-view series): a floor read from a frame the object reaches (the 20,000-atom a-Si's frame read
12.2 at 303 standard errors, with no floor simulated) stayed wrong for the run, its misfit grew
Gaussians in the vacuum, and the run trained to step 3,000 (docs/performance.md).

Where the views' fits agree within their noise (:func:`agree`, tested every ``refine_every``
steps) the views share one floor, fitted to every view's latest equations: a detector offset is
the same in every view, and one view's fit is noisier than all views' by the square root of
their number (the peer's aSi-208 counts at a dose of 8e3 e/Å²: one view's frame reads its
1.0-count floor to 1.4%).  A floor that varies within the views keeps its own per view (its
fixed frame surface differs between the views).
"""

from __future__ import annotations

import math

import torch

from gaussian_atoms_method.engine.console import CONSOLE
from gaussian_atoms_method.engine.noise_reading import FLOOR_Z
from gaussian_atoms_method.engine.rendering import FLOOR_TERMS, index_on


def floor_moments(weights: torch.Tensor, row_powers: torch.Tensor, col_powers: torch.Tensor) -> torch.Tensor:
    """(V, A, B): ``sum over pixels of weights * row^a * col^b`` of each (V, H, W) ``weights``
    image, for the (A, H) and (B, W) powers of the coordinates (:func:`.rendering.coordinate_powers`):
    two small matrix products, not one image per term."""
    return row_powers @ weights @ col_powers.T


def _solve(gram: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
    """``gram^-1 rhs`` for (..., K, K) and (..., K), with a ridge of 1e-9 of the mean diagonal so
    that a view with no background pixel (all zeros) gets zero; ``solve_ex`` does not wait for
    the GPU to check for errors."""
    k = gram.shape[-1]
    ridge = 1e-9 * gram.diagonal(dim1=-2, dim2=-1).mean(-1)[..., None, None] + 1e-300
    return torch.linalg.solve_ex(gram + ridge * torch.eye(k, dtype=gram.dtype, device=gram.device), rhs[..., None])[0][
        ..., 0
    ]


def agree(values: torch.Tensor, gram: torch.Tensor, z: float = FLOOR_Z) -> tuple[bool, torch.Tensor]:
    """Whether the (V, K) per-view ``values``, each with inverse covariance ``gram`` (V, K, K),
    are one value measured V times, and that value (K,), their inverse-covariance-weighted mean.
    One value when their chi-square about it stays within ``z`` standard deviations
    (``sqrt(2 dof)``) of its ``K (V - 1)`` degrees of freedom."""
    pooled = _solve(gram.sum(0), (gram @ values[..., None]).sum(0)[:, 0])
    d = values - pooled
    chi2 = float((d[:, None, :] @ gram @ d[..., None]).sum())
    dof = values.shape[1] * (len(values) - 1)
    return dof > 0 and chi2 <= dof + z * math.sqrt(2.0 * dof), pooled


OBJECT_FREE = 0.1
"""A pixel is background where the Gaussians put less than this many noise standard deviations
on it: a misfit of a tenth of the object's own signal there biases the floor by a hundredth of
the noise, under the standard error of a floor pooled over 10,000 pixels.  Fitted over the
object too, the floor takes the object's misfit: on the peer's aSi-208 at 8e3 e/Å² it read
28.14 against the empty frame's 28.7 ± 0.05 (normalised units), and the residual it left grew
false atoms."""


def background_weights(model, predicted: torch.Tensor, floors: torch.Tensor) -> torch.Tensor:
    """(V, H, W) the weights of the floor's fit over the pixels of the views' ``predicted``
    projections, whose ``floors`` are given: one over the noise variance at the predicted level
    where the Gaussians put less than :data:`OBJECT_FREE` noise deviations, zero on the object.
    Without a noise model, one everywhere."""
    noise = model.noise_read
    if noise is None:
        return torch.ones_like(predicted)
    variance = noise.variance(predicted).to(predicted.dtype).clamp_min(1e-30)
    return torch.where(predicted - floors < OBJECT_FREE * variance.sqrt(), 1.0 / variance, 0.0)


class FloorSolver:
    """Each view's latest normal equations and the floors they give.

    A view's equations are replaced each time it is rendered (:meth:`accumulate`), and its floor
    moves to their fit at once; a shared floor moves to the fit of every view's latest equations
    (their sum), so one view's noise moves it by a share of the views', not all of it.  Every
    ``refine_every`` steps :meth:`decide` tests whether the views' fits agree.  The equations
    are the weights' and the weighted residual's moments in the detector coordinates
    (:func:`floor_moments`), on the run's device without waiting for it."""

    def __init__(self) -> None:
        self.gram: torch.Tensor | None = None  # (V, K, K): each view's latest normal matrix
        self.target: torch.Tensor | None = None  # (V, K): gram @ (its floor's fit)
        self.shared = False
        self._terms: dict = {}  # (terms, device) -> the terms' powers and their pairs' sums there

    @torch.no_grad()
    def accumulate(self, model, predicted: torch.Tensor, measured: torch.Tensor) -> None:
        """Replace the normal equations of the views the model last rendered with their floors
        (``model.rendered_floors``: their indices, the detector's :func:`.rendering.coordinate_powers`
        and the (V, H, W) floors as rendered; in training only) by those
        of ``predicted`` and ``measured`` (V, H, W, 1) or (H, W, 1), and move the floors to
        their fit."""
        if not model.training or model.rendered_floors is None:
            return
        views, (row_powers, col_powers), floors = model.rendered_floors
        coefficients = model.view_params["background"]
        n_views, k = coefficients.shape
        h, w = predicted.shape[-3:-1]
        predicted, measured = predicted.detach().reshape(-1, h, w), measured.to(predicted).reshape(-1, h, w)
        dev = predicted.device
        index = index_on(views, dev)
        current = coefficients.data.to(dev)[index].double()  # (V, K)
        terms = self._terms.get((k, dev))
        if terms is None:  # made once per device: the terms' powers (K, 2) and their pairs' sums (K, K, 2)
            powers = index_on(FLOOR_TERMS[:k], dev)
            terms = self._terms[(k, dev)] = (
                powers[:, 0],
                powers[:, 1],
                *(powers[:, None, :] + powers[None, :, :]).unbind(-1),
            )
        row_terms, col_terms, row_pairs, col_pairs = terms
        weight = background_weights(model, predicted, floors.reshape(-1, h, w))  # the floors as rendered
        gram = floor_moments(weight, row_powers, col_powers).double()[:, row_pairs, col_pairs]  # (V, K, K)
        # (V, K)
        rhs = floor_moments(weight * (measured - predicted), row_powers[:3], col_powers[:3]).double()[
            :, row_terms, col_terms
        ]
        if self.gram is None or self.gram.shape[:2] != (n_views, k) or self.gram.device != dev:
            self.gram = torch.zeros(n_views, k, k, dtype=torch.float64, device=dev)
            self.target = torch.zeros(n_views, k, dtype=torch.float64, device=dev)
        self.gram[index] = gram
        self.target[index] = (gram @ current[..., None])[..., 0] + rhs
        if self.shared:
            coefficients.data[:] = self._pooled().to(coefficients)
        else:  # a view with no background pixel keeps its floor
            coefficients.data[index.to(coefficients.device)] = (current + _solve(gram, rhs)).to(coefficients)

    def _seen(self) -> torch.Tensor:
        return self.gram.diagonal(dim1=1, dim2=2)[:, 0] > 0

    def _pooled(self) -> torch.Tensor:
        return _solve(self.gram.sum(0), self.target.sum(0))  # a view not rendered yet adds zeros

    @torch.no_grad()
    def decide(self, model, step: int) -> None:
        """At each ``refine_every`` steps of the model's config after the first (else nothing):
        share one floor among the views while their latest fits agree (:func:`agree`) and the
        floor has no fixed per-view surface, else fit each view's own."""
        if self.gram is None or step == 0 or step % model.config.refine_every or len(model.background_surfaces):
            return
        seen = self._seen()
        gram = self.gram[seen]
        fitted = _solve(gram, self.target[seen])
        shared, pooled = agree(fitted, gram)
        coefficients = model.view_params["background"]
        if shared:
            coefficients.data[:] = pooled.to(coefficients)
        if shared != self.shared:
            self.shared = shared
            CONSOLE.print(
                f"gaussian-atoms: step {step}: "
                + (
                    "the views' floors agree within their noise: one floor for all views"
                    if shared
                    else "the views' floors differ beyond their noise: each view's fitted on its own"
                )
            )
