"""Each atom's evidence (atoms/evidence.py, atoms/information.py) against direct computations in
float64: the closed-form information against pixel sums of autograd's derivatives, an atom taken out against the cost of
its neighbours actually re-fitted without it, the depth interval against the profile of the cost
on a missing-wedge series, and the residual spectrum's weight against noise of known colour."""

import numpy as np
import pytest
import torch

from gaussian_atoms_method.atoms.evidence import Z95, atom_evidence, proof_level
from gaussian_atoms_method.atoms.information import pair_information, residual_spectrum_factors
from gaussian_atoms_method.physics.geometry import detector_axes_from_tilts

PIXEL_A = 0.2
GRID = (np.arange(-40, 41) * PIXEL_A,) * 2


def _render(params: torch.Tensor, axes: np.ndarray) -> torch.Tensor:
    """(V, H, W) pixel images of atoms ``params`` (K, 5): x, y, z, sigma, q (float64, exact)."""
    u, w = (torch.tensor(g) for g in np.meshgrid(*GRID, indexing="ij"))
    axes_t = torch.tensor(axes[:, :2])
    mu = torch.einsum("vkc,nc->nvk", axes_t, params[:, :3])
    sigma, q = params[:, 3], params[:, 4]
    d2 = (u[None, None] - mu[..., 0, None, None]) ** 2 + (w[None, None] - mu[..., 1, None, None]) ** 2
    peak = (q * sigma * np.sqrt(2 * np.pi))[:, None, None, None]
    return (peak * torch.exp(-d2 / (2 * sigma[:, None, None, None] ** 2))).sum(0)


def test_the_information_is_the_pixel_sum_of_the_derivatives():
    axes = detector_axes_from_tilts(np.linspace(-60, 60, 5))
    params = torch.tensor([[0.2, -0.1, 0.3, 0.5, 1.3], [0.9, 0.4, -0.5, 0.7, 0.8]], dtype=torch.float64)
    jac = torch.autograd.functional.jacobian(
        lambda p: torch.stack([_render(p[k : k + 1], axes) for k in range(2)]),
        params,
        vectorize=True,
        strategy="forward-mode",
    )  # (2, V, H, W, 2, 5)
    flat = [jac[k].reshape(-1, 2, 5)[:, k] for k in range(2)]
    p = params.numpy()
    for i, j in [(0, 1), (0, 0), (1, 1)]:
        direct = (flat[i].T @ flat[j]).numpy()
        ours = pair_information(p[[i], :3], p[[j], :3], p[[i], 3], p[[j], 3], p[[i], 4], p[[j], 4], axes, PIXEL_A)
        # the pixel sum equals the integral / p^2 far below float64's 1e-12 for sigma >= 2.5 px
        np.testing.assert_allclose(ours[0], direct, rtol=1e-9, atol=1e-12 * np.abs(direct).max())


def test_a_view_informs_an_atom_by_the_share_of_it_on_the_detector():
    """A film's atom near the detector's edge is seen in part: the information is the pixel sum
    over the detector alone.  An atom centred on the edge keeps exactly half of every diagonal
    entry (its squared derivatives are even about its centre; the cross terms a cut makes are what
    the share leaves out); one inside keeps all of it, one beyond nothing."""
    from gaussian_atoms_method.atoms.information import DetectorField

    axes = detector_axes_from_tilts(np.array([0.0]))
    edge_A = -0.1  # between the pixels at -0.2 and 0 Å: the detector holds the rows below it
    rows = torch.tensor(GRID[0] < edge_A)
    field = DetectorField((GRID[0][0] - PIXEL_A / 2, edge_A), (GRID[1][0] - PIXEL_A / 2, GRID[1][-1] + PIXEL_A / 2))
    inside, centred, beyond = [-3.0, 0.4, 0.0], [edge_A, 0.4, 0.0], [3.0, 0.4, 0.0]
    for place, kept in ((inside, 1.0), (centred, 0.5), (beyond, 0.0)):
        params = torch.tensor([[*place, 0.5, 1.3]], dtype=torch.float64)
        jac = torch.autograd.functional.jacobian(lambda p: _render(p, axes), params, vectorize=True)
        on_detector = jac[0][rows].reshape(-1, 5)  # (pixels on the detector, 5)
        direct = (on_detector.T @ on_detector).numpy()
        p = params.numpy()
        whole = pair_information(p[:, :3], p[:, :3], p[:, 3], p[:, 3], p[:, 4], p[:, 4], axes, PIXEL_A)[0]
        ours = pair_information(
            p[:, :3], p[:, :3], p[:, 3], p[:, 3], p[:, 4], p[:, 4], axes, PIXEL_A, sight=field.sight(axes)
        )[0]
        free = [0, 1, 3, 4]  # x, y, width, peak (one view along z: no depth)
        np.testing.assert_allclose(np.diag(ours)[free], kept * np.diag(whole)[free], rtol=1e-9, atol=1e-12)
        # the pixel sum over the detector: a pixel edge on the cut, sigma 2.5 px
        np.testing.assert_allclose(np.diag(ours)[free], np.diag(direct)[free], rtol=1e-6, atol=1e-9 * whole.max())
    assert field.cuts(axes, np.array([centred]), np.array([0.5]))
    assert not field.cuts(axes, np.array([inside]), np.array([0.5]))


def _refit(params: torch.Tensor, free: torch.Tensor, target: torch.Tensor, axes, steps=60) -> float:
    """The least-squares cost of ``params`` with the entries ``free`` re-fitted to ``target``
    (Gauss-Newton, float64)."""
    params = params.clone()

    def residual(values):
        p = params.clone()
        p[free] = values
        return (_render(p, axes) - target).reshape(-1)

    values = params[free].clone()
    for _ in range(steps):
        r = residual(values)
        jac = torch.autograd.functional.jacobian(residual, values, vectorize=True, strategy="forward-mode")
        step = torch.linalg.lstsq(jac, -r[:, None]).solution[:, 0]
        values = values + step
        if step.abs().max() < 1e-12:
            break
    return float((residual(values) ** 2).sum())


def test_an_atom_taken_out_costs_what_its_neighbours_cannot_take_up():
    """Three atoms in a row 2.4 Å apart (one sigma of overlap per side), seen over +-60 degrees:
    the middle one taken out, its neighbours re-fitted (positions, widths, amplitudes), leaves a
    misfit whose square root in noise units is the stated significance.  The statement is the
    quadratic limit; the neighbours' actual re-fit moves them by a fraction of their width, so the
    two agree to a few percent, and the significance is well below what the atom alone would
    carry (its neighbours take up part of it)."""
    axes = detector_axes_from_tilts(np.linspace(-60, 60, 9))
    atoms = torch.tensor(
        [[-2.4, 0.0, 0.0, 0.55, 1.0], [0.0, 0.0, 0.3, 0.55, 0.6], [2.4, 0.0, 0.0, 0.55, 1.0]], dtype=torch.float64
    )
    target = _render(atoms, axes)
    noise = 0.05
    p = atoms.numpy()
    stated = atom_evidence(p[:, :3], p[:, 3], p[:, 4], axes, PIXEL_A, noise).significance[1]
    without = atoms.clone()
    without[1, 4] = 0.0
    free = torch.zeros_like(atoms, dtype=torch.bool)
    free[[0, 2]] = True
    actual = np.sqrt(_refit(without, free, target, axes)) / noise
    assert stated == pytest.approx(actual, rel=0.05)
    alone = np.sqrt(float((_render(atoms[1:2], axes) ** 2).sum())) / noise
    assert stated < 0.95 * alone


def test_the_depth_interval_is_the_profile_of_the_cost_along_the_beam():
    """One atom seen over +-50 degrees about y (a missing wedge): the direction fixed least is
    the beam, and the 95% half-width along it is where the cost, every other parameter
    re-fitted, has risen by 1.96^2 noise variances.  A hard core four times that half-width
    leaves the atom closed in depth, one under it open."""
    axes = detector_axes_from_tilts(np.linspace(-50, 50, 11))
    atom = torch.tensor([[0.1, -0.2, 0.15, 0.5, 0.3]], dtype=torch.float64)
    target = _render(atom, axes)
    noise = 0.2
    p = atom.numpy()
    ev = atom_evidence(p[:, :3], p[:, 3], p[:, 4], axes, PIXEL_A, noise, hard_core_A=None)
    half = ev.depth_halfwidth_A[0]
    assert abs(ev.depth_axis[0, 2]) > 0.999  # the beam
    assert ev.position_std_A[0, 2] > 1.3 * ev.position_std_A[0, 0]  # the wedge: z fixed less than x
    moved = atom.clone()
    moved[0, 2] += half
    free = torch.ones_like(atom, dtype=torch.bool)
    free[0, 2] = False
    rise = _refit(moved, free, target, axes) / noise**2
    assert rise == pytest.approx(Z95**2, rel=0.05)
    closed = atom_evidence(p[:, :3], p[:, 3], p[:, 4], axes, PIXEL_A, noise, hard_core_A=4.1 * half)
    opened = atom_evidence(p[:, :3], p[:, 3], p[:, 4], axes, PIXEL_A, noise, hard_core_A=3.9 * half)
    assert not closed.depth_open[0] and opened.depth_open[0]


def test_proof_level_and_labels():
    """The level is Bonferroni's over the atoms (5% family-wise); an atom whose amplitude is
    a tenth of the noise's reach is open, a strong one proven."""
    assert proof_level(1) == pytest.approx(1.6449, abs=1e-4)
    assert proof_level(10_000) == pytest.approx(4.4172, abs=1e-4)
    axes = detector_axes_from_tilts(np.linspace(-60, 60, 9))
    p = np.array([[0.0, 0.0, 0.0, 0.5, 1.0], [10.0, 0.0, 0.0, 0.5, 1.0]])
    alone = atom_evidence(p[:1, :3], p[:1, 3], p[:1, 4], axes, PIXEL_A, 1.0).significance[0]
    p[1, 4] = 0.1 * proof_level(2) / alone  # a tenth of the level
    ev = atom_evidence(p[:, :3], p[:, 3], p[:, 4], axes, PIXEL_A, 1.0)
    assert ev.significance[1] == pytest.approx(0.1 * proof_level(2), rel=1e-6)
    assert not ev.proven[1] and ev.proven[0] == (alone >= proof_level(2))


def test_the_residual_spectrum_weighs_coloured_noise_at_the_atoms_scale():
    """White noise weighs 1 (within its sampling scatter); the same variance smoothed over two
    pixels weighs far more on an amplitude's template, which integrates over the atom, than
    white noise does."""
    from scipy import ndimage

    rng = np.random.default_rng(0)
    white = rng.normal(0, 3.0, size=(20, 96, 96))
    position, amplitude = residual_spectrum_factors(white, 3.0, 2.0)
    assert position == pytest.approx(1.0, abs=0.03) and amplitude == pytest.approx(1.0, abs=0.03)
    smooth = ndimage.gaussian_filter(white, (0, 2, 2))
    smooth *= 3.0 / smooth.std()
    position, amplitude = residual_spectrum_factors(smooth, 3.0, 2.0)
    assert amplitude > 2.0 and amplitude > position


def test_the_sandwich_is_the_information_under_white_noise_and_wider_under_misregistration():
    """Ten atoms far apart, 40 views over +-60 degrees.  Where the residual is white noise of
    standard deviation s, the views' pulls spread as ``s^2 F`` and the sandwich's precision is the
    information's (within the scatter of 40 clusters: about 11% on a standard deviation, a
    median over ten atoms far less).  Where each view is also shifted by 0.3 px, a residual no
    white noise of its level explains, the sandwich widens the precision along the shifts."""
    from gaussian_atoms_method.atoms.information import view_scores
    from gaussian_atoms_method.physics.geometry import pixel_centres
    from gaussian_atoms_method.physics.projector import project_gaussians

    rng = np.random.default_rng(5)
    axes = detector_axes_from_tilts(np.linspace(-60, 60, 40))
    px, n = 0.25, 10
    positions = np.c_[np.linspace(-9, 9, n), rng.uniform(-2, 2, n), rng.uniform(-2, 2, n)]
    sigmas, amps = np.full(n, 0.5), np.full(n, 1.0)
    coords = torch.tensor(pixel_centres(96, px))
    clean = project_gaussians(
        torch.tensor(positions), torch.tensor(sigmas), torch.tensor(amps), torch.tensor(axes), coords, coords
    ).numpy()
    centre = ((96 - 1) / 2, (96 - 1) / 2)
    s = 0.02
    residual = rng.normal(0, s, clean.shape)
    information = atom_evidence(positions, sigmas, amps, axes, px, s).position_std_A
    pulls = view_scores(positions, sigmas, amps, axes, residual, px, centre)
    sandwich = atom_evidence(positions, sigmas, amps, axes, px, s, scores=pulls).position_std_A
    assert np.median(sandwich / information, axis=0) == pytest.approx([1, 1, 1], abs=0.1)
    width_information = atom_evidence(positions, sigmas, amps, axes, px, s).width_std_A
    width_sandwich = atom_evidence(positions, sigmas, amps, axes, px, s, scores=pulls).width_std_A
    assert np.median(width_sandwich / width_information) == pytest.approx(1, abs=0.1)
    from scipy import ndimage

    shifted = np.stack([ndimage.shift(v, (0.3 * rng.standard_normal(), 0), order=3) for v in clean])
    pulls = view_scores(positions, sigmas, amps, axes, shifted - clean + residual, px, centre)
    misregistered = atom_evidence(positions, sigmas, amps, axes, px, s, scores=pulls).position_std_A
    assert np.median(misregistered[:, 0] / information[:, 0]) > 2.0  # x: across the tilt axis


def test_the_views_pulls_are_the_gradient_a_known_move_leaves():
    """An atom's image moved by a known step, or its width and mass changed a little: the views'
    pulls on the unmoved atom, through its information, give that step back (one Gauss-Newton
    step: exact to first order; at a twentieth of the width the second order stays within 2% of
    the step.  A move's second order looks like a wider atom: after a move, the position is judged)."""
    from gaussian_atoms_method.atoms.information import view_scores
    from gaussian_atoms_method.physics.geometry import pixel_centres
    from gaussian_atoms_method.physics.projector import project_gaussians

    axes = detector_axes_from_tilts(np.linspace(-60, 60, 25))
    px, coords = 0.25, torch.tensor(pixel_centres(80, 0.25))

    def image(p):
        return project_gaussians(
            torch.tensor(p[None, :3]), torch.tensor(p[3:4]), torch.tensor(p[4:5]), torch.tensor(axes), coords, coords
        ).numpy()

    atom = np.array([0.3, -0.2, 0.4, 0.5, 1.0])
    information = pair_information(
        atom[None, :3], atom[None, :3], atom[3:4], atom[3:4], atom[4:5], atom[4:5], axes, px
    )[0]
    for step, judged in (
        (np.array([0.02, -0.01, 0.025, 0.0, 0.0]), slice(0, 3)),
        (np.array([0, 0, 0, 0.002, 0.004]), slice(0, 5)),
    ):
        residual = image(atom + step) - image(atom)
        pulls = view_scores(atom[None, :3], atom[3:4], atom[4:5], axes, residual, px, (39.5, 39.5))
        found = np.linalg.solve(information, pulls[0].sum(0))
        np.testing.assert_allclose(found[judged], step[judged], atol=0.02 * np.abs(step).max())


def test_the_depth_profile_is_the_cost_of_the_atom_moved_with_the_rest_refitted():
    """Beyond second order: two atoms 2.6 Å apart over +-50 degrees, noise added; one moved along
    the beam by 1, 2 and 3 halves of a 1 Å hard core either way, everything else (its own place
    across the beam, width, mass; its neighbour) re-fitted by Gauss-Newton to convergence: the
    stated rises (linearised about the moved place) are that cost within 5%.  Under noise
    120 times larger every rise falls under 1.96^2 and the atom is open in depth."""
    from gaussian_atoms_method.atoms.depth_profile import depth_profile_pulls
    from gaussian_atoms_method.atoms.information import view_scores

    axes = detector_axes_from_tilts(np.linspace(-50, 50, 11))
    atoms = torch.tensor([[0.1, -0.2, 0.15, 0.5, 0.3], [2.6, 0.1, -0.4, 0.5, 0.3]], dtype=torch.float64)
    clean = _render(atoms, axes)
    noise = 0.02
    measured = clean + torch.as_tensor(np.random.default_rng(0).normal(0, noise, clean.shape))
    p, residual, centre = atoms.numpy(), (measured - clean).numpy(), (40.0, 40.0)
    pulls = view_scores(p[:, :3], p[:, 3], p[:, 4], axes, residual, PIXEL_A, centre)
    moved = depth_profile_pulls(p[:, :3], p[:, 3], p[:, 4], axes, residual, PIXEL_A, centre, 1.0)
    ev = atom_evidence(p[:, :3], p[:, 3], p[:, 4], axes, PIXEL_A, noise, 1.0, scores=pulls, moved_pulls=moved)
    np.testing.assert_allclose(ev.depth_offsets_A, [-1.5, -1.0, -0.5, 0.5, 1.0, 1.5])
    base = float(((clean - measured) ** 2).sum())
    free = torch.ones_like(atoms, dtype=torch.bool)
    free[0, 2] = False
    for offset, stated in zip(ev.depth_offsets_A, ev.depth_profile[0]):
        shifted = atoms.clone()
        shifted[0, 2] += offset
        actual = (_refit(shifted, free, measured, axes) - base) / noise**2
        assert stated == pytest.approx(actual, rel=0.05)
    assert not ev.depth_open[0]
    loud = atom_evidence(p[:, :3], p[:, 3], p[:, 4], axes, PIXEL_A, 120 * noise, 1.0, scores=pulls, moved_pulls=moved)
    assert np.all(loud.depth_profile[0] < Z95**2) and loud.depth_open[0] and loud.depth_halfwidth_A[0] >= 1.5


def test_a_place_within_a_neighbours_hard_core_is_the_column_moved_as_one():
    """An atom with a neighbour 1.75 Å below it, nearly along the beam (hard core 1.4 Å): moved
    down by half a hard core or more it would come within the neighbour's hard core, so the two
    move as one column (before, such a place was no atom's and the profile said nothing there),
    and the stated rise is the cost of the column moved with everything else re-fitted (both
    places along the beam held), within 5% as for one atom.  (Moved up, the atom goes alone; with
    a neighbour this close along the beam the exact re-fit drags the neighbour after it by more
    than a linearised step can, and the stated rise is 1.2-1.6 times the exact one: the profile
    errs towards calling such an atom's depth closed.)"""
    from gaussian_atoms_method.atoms.depth_profile import depth_profile_pulls
    from gaussian_atoms_method.atoms.information import view_scores

    axes = detector_axes_from_tilts(np.linspace(-50, 50, 11))
    atoms = torch.tensor(
        [[0.1, -0.2, 0.15, 0.5, 0.3], [2.6, 0.1, -0.4, 0.5, 0.3], [0.25, -0.1, -1.6, 0.5, 0.3]], dtype=torch.float64
    )
    clean = _render(atoms, axes)
    noise = 0.02
    measured = clean + torch.as_tensor(np.random.default_rng(1).normal(0, noise, clean.shape))
    p, residual, centre = atoms.numpy(), (measured - clean).numpy(), (40.0, 40.0)
    pulls = view_scores(p[:, :3], p[:, 3], p[:, 4], axes, residual, PIXEL_A, centre)
    moved = depth_profile_pulls(p[:, :3], p[:, 3], p[:, 4], axes, residual, PIXEL_A, centre, 1.4)
    ev = atom_evidence(p[:, :3], p[:, 3], p[:, 4], axes, PIXEL_A, noise, 1.4, scores=pulls, moved_pulls=moved)
    assert np.isfinite(ev.depth_profile[0]).all()
    base = float(((clean - measured) ** 2).sum())
    for offset, stated in zip(ev.depth_offsets_A[:3], ev.depth_profile[0, :3]):
        column = [0, 2]
        shifted = atoms.clone()
        shifted[column, 2] += offset
        free = torch.ones_like(atoms, dtype=torch.bool)
        free[column, 2] = False
        actual = (_refit(shifted, free, measured, axes) - base) / noise**2
        assert stated == pytest.approx(actual, rel=0.05)


def test_an_atom_the_fit_left_off_its_depth_is_open_in_depth():
    """Two atoms 2.6 Å apart over +-50 degrees; the views hold the first 1 Å higher than the
    fit put it (a fit ended off its optimum along the beam; hard core 1.4 Å, so the profile
    looks 0.7, 1.4 and 2.1 Å either way).  Moved up by 0.7 or 1.4 Å it comes within 0.4 Å of
    where it is: the cost falls by thousands of noise variances even with nothing else
    re-fitted, an exact bound, so the views prefer that place and the atom is open in depth,
    its interval reaching it.  The atom fitted where the views hold it is closed
    (the test above)."""
    from gaussian_atoms_method.atoms.depth_profile import depth_profile_pulls
    from gaussian_atoms_method.atoms.information import view_scores

    axes = detector_axes_from_tilts(np.linspace(-50, 50, 11))
    truth = torch.tensor([[0.1, -0.2, 1.15, 0.5, 0.3], [2.6, 0.1, -0.4, 0.5, 0.3]], dtype=torch.float64)
    fitted = truth.clone()
    fitted[0, 2] -= 1.0
    noise = 0.02
    clean = _render(truth, axes)
    measured = clean + torch.as_tensor(np.random.default_rng(2).normal(0, noise, clean.shape))
    p, residual, centre = fitted.numpy(), (measured - _render(fitted, axes)).numpy(), (40.0, 40.0)
    pulls = view_scores(p[:, :3], p[:, 3], p[:, 4], axes, residual, PIXEL_A, centre)
    moved = depth_profile_pulls(p[:, :3], p[:, 3], p[:, 4], axes, residual, PIXEL_A, centre, 1.4)
    ev = atom_evidence(p[:, :3], p[:, 3], p[:, 4], axes, PIXEL_A, noise, 1.4, scores=pulls, moved_pulls=moved)
    up = ev.depth_offsets_A > 0
    np.testing.assert_allclose(ev.depth_offsets_A[up], [0.7, 1.4, 2.1])
    assert np.all(ev.depth_profile[0, up][:2] < -1000) and ev.depth_profile[0, up][2] > Z95**2
    assert ev.depth_open[0] and ev.depth_halfwidth_A[0] >= 1.4


def _cluster(n: int, seed: int = 0):
    """An amorphous Pd cluster of ``n`` atoms seen over a 29-view limited series, each atom with
    its own width and mass, views' pulls and moved pulls drawn at random (the algebra does not
    care that they are not a fit's)."""
    from gaussian_atoms_method.harness.particles import amorphous_packing

    rng = np.random.default_rng(seed)
    positions = amorphous_packing(n, ("Pd",), 2.5, rng).positions
    axes = detector_axes_from_tilts(np.linspace(-70, 70, 29))
    sigmas, amps = rng.uniform(0.3, 0.45, n), rng.uniform(50, 80, n)
    scores = rng.normal(0, 5.0, (n, 29, 5))
    moved = {o: rng.normal(0, 20.0, (n, 5)) for o in (-1.5, -0.75, 0.75, 1.5)}
    return positions, sigmas, amps, axes, scores, moved


def test_atoms_solved_together_are_each_alone(monkeypatch):
    """The local solves run in batches of atoms with as many neighbours (and batches cut to a
    budget); every atom's evidence is the same, to rounding, as when it is asked for alone."""
    import gaussian_atoms_method.atoms.information as information

    positions, sigmas, amps, axes, scores, moved = _cluster(120)
    kw = dict(hard_core_A=1.5, scores=scores, moved_pulls=moved)
    monkeypatch.setattr(information, "BATCH_ELEMENTS", 2e5)  # batches of a few atoms
    together = atom_evidence(positions, sigmas, amps, axes, 0.4, 10.0, **kw)
    assert np.isfinite(together.significance).all()
    for a in (0, 17, 60, 119):
        alone = atom_evidence(positions, sigmas, amps, axes, 0.4, 10.0, targets=np.arange(120) == a, **kw)
        for name in ("significance", "position_std_A", "depth_halfwidth_A", "depth_profile"):
            np.testing.assert_allclose(getattr(alone, name)[a], getattr(together, name)[a], rtol=1e-9)


def test_a_dense_sets_information_is_positive_and_its_neighbours_only_lower_the_evidence():
    """In a dense light-element cluster (carbon's bonds, 1.4 Å, atoms 0.64 Å wide: an atom couples
    to some 60 others) each atom's set is a principal submatrix of the whole information, so
    positive definite; and re-fitting neighbours can only lower the cost of taking an atom out:
    each significance lies at or below the atom's alone (before the blocks between neighbours were
    kept, 30% of a carbon particle's atoms read 1e151).  The pairs among neighbours are those a
    plain loop over each atom's neighbours finds."""
    from gaussian_atoms_method.atoms.evidence import COUPLING_FLOOR
    from gaussian_atoms_method.atoms.information import amplitude_coupling, local_information, pairs_among_neighbours
    from gaussian_atoms_method.harness.particles import amorphous_packing

    rng = np.random.default_rng(3)
    positions = amorphous_packing(300, ("C",), 1.4, rng).positions
    axes = detector_axes_from_tilts(np.arange(-72, 73, 4.0))
    sigmas, amps = np.full(300, 0.64), rng.uniform(25, 35, 300)
    ev = atom_evidence(positions, sigmas, amps, axes, 0.34, 5.0)
    alone = np.array(
        [
            atom_evidence(positions[a : a + 1], sigmas[a : a + 1], amps[a : a + 1], axes, 0.34, 5.0).significance[0]
            for a in range(0, 300, 30)
        ]
    )
    assert np.all(ev.significance[::30] <= alone * (1 + 1e-9))
    assert np.all(ev.significance > 0) and np.all(np.isfinite(ev.position_std_A))
    i, j = np.triu_indices(300, 1)
    near = amplitude_coupling(positions[i], positions[j], sigmas[i], sigmas[j], axes) >= COUPLING_FLOOR
    neighbours = np.stack([i[near], j[near]], axis=1)
    pairs = np.concatenate([neighbours, pairs_among_neighbours(neighbours, 300)])
    near_of = {a: set() for a in range(300)}
    for i_, j_ in neighbours.tolist():
        near_of[i_].add(j_), near_of[j_].add(i_)
    among = {(p, q) for ns in near_of.values() for p in ns for q in ns if p < q} - set(map(tuple, neighbours.tolist()))
    np.testing.assert_array_equal(pairs[len(neighbours) :], np.array(sorted(among)).reshape(-1, 2))
    blocks = pair_information(
        positions[pairs[:, 0]],
        positions[pairs[:, 1]],
        sigmas[pairs[:, 0]],
        sigmas[pairs[:, 1]],
        amps[pairs[:, 0]],
        amps[pairs[:, 1]],
        axes,
        0.34,
    )
    diagonal = pair_information(positions, positions, sigmas, sigmas, amps, amps, axes, 0.34)
    sizes = []
    for _, local, info in local_information(np.arange(0, 300, 7), neighbours, pairs, blocks, diagonal, 0):
        info = info.numpy()
        scale = np.sqrt(np.einsum("bii->bi", info))
        sizes.append(local.shape[1])
        assert np.linalg.eigvalsh(info / scale[:, :, None] / scale[:, None, :]).min() > 0
    assert max(sizes) > 20  # sets as dense as carbon's


def test_the_amplitude_coupling_is_the_informations():
    """The coupling that picks an atom's neighbours, read without the rest of the blocks, is
    ``|F_qiqj| / sqrt(F_qiqi F_qjqj)`` of the full information, and 1 for an atom with itself."""
    from gaussian_atoms_method.atoms.information import amplitude_coupling

    positions, sigmas, amps, axes, _, _ = _cluster(60, seed=1)
    i, j = np.triu_indices(60, 1)
    blocks = pair_information(positions[i], positions[j], sigmas[i], sigmas[j], amps[i], amps[j], axes, 0.4)
    own = pair_information(positions, positions, sigmas, sigmas, amps, amps, axes, 0.4)
    rho = np.abs(blocks[:, 4, 4]) / np.sqrt(own[i, 4, 4] * own[j, 4, 4])
    np.testing.assert_allclose(amplitude_coupling(positions[i], positions[j], sigmas[i], sigmas[j], axes), rho)
    np.testing.assert_allclose(amplitude_coupling(positions, positions, sigmas, sigmas, axes), 1.0)


def test_read_only_atoms_give_the_same_information_without_a_warning():
    """An AtomSet's or a memory map's arrays are read-only: the information is the same, and torch
    is not handed them to share (it warns that writing would be undefined)."""
    import warnings

    positions, sigmas, amps, axes, _, _ = _cluster(20, seed=4)
    want = pair_information(positions, positions, sigmas, sigmas, amps, amps, axes, 0.4)
    for a in (positions, sigmas, amps, axes):
        a.flags.writeable = False
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = pair_information(positions, positions, sigmas, sigmas, amps, amps, axes, 0.4)
    np.testing.assert_array_equal(got, want)


def test_the_views_pulls_in_torch_are_numpys():
    """:func:`view_scores` batched in torch (a GPU's way) equals the host's numpy, view by view,
    atoms near and beyond the detector's edges included."""
    from gaussian_atoms_method.atoms.information import view_scores
    from gaussian_atoms_method.physics.devices import HOST

    rng = np.random.default_rng(2)
    positions = rng.uniform(-22, 22, (300, 3))
    sigmas, amps = rng.uniform(0.3, 0.9, 300), rng.uniform(10, 80, 300)
    axes = detector_axes_from_tilts(np.linspace(-70, 70, 9))
    residual = rng.normal(0, 3, (9, 120, 90))
    host = view_scores(positions, sigmas, amps, axes, residual, 0.4, (60, 45), device=HOST)
    batched = view_scores(positions, sigmas, amps, axes, torch.as_tensor(residual), 0.4, (60, 45), device="cpu")
    np.testing.assert_allclose(batched, host, rtol=1e-10, atol=1e-10 * np.abs(host).max())


def _fcc_evidence_inputs():
    """150 atoms of an fcc lattice (columns along the beam, so the depth profile moves several
    atoms at once), a 15-view series and a noise residual: :func:`atom_evidence`'s arguments and
    the moved pulls."""
    from gaussian_atoms_method.atoms.depth_profile import depth_profile_pulls
    from gaussian_atoms_method.atoms.information import view_scores

    rng = np.random.default_rng(5)
    cells = np.stack(np.meshgrid(*(np.arange(4),) * 3, indexing="ij"), -1).reshape(-1, 3)
    basis = np.array([[0, 0, 0], [0.5, 0.5, 0], [0.5, 0, 0.5], [0, 0.5, 0.5]])
    positions = ((cells[:, None] + basis[None]).reshape(-1, 3) * 4.08 - 6.0)[:150]
    sigmas, amps = rng.uniform(0.5, 0.6, 150), rng.uniform(80, 120, 150)
    axes = detector_axes_from_tilts(np.arange(-70, 71, 10))
    residual = rng.normal(0, 5, (len(axes), 90, 90))
    args = (positions, sigmas, amps, axes, residual, 0.3, (45, 45))
    pulls, moved = view_scores(*args), depth_profile_pulls(*args, 1.8)
    return (positions, sigmas, amps, axes, 0.3, 5.0, 1.8, "l2", 1.0, 1.0, pulls), moved


def test_the_depth_profile_from_the_hosts_table_of_moved_blocks_is_the_one_read_batch_by_batch(monkeypatch):
    """The host reads each moved atom's block once (:class:`~gaussian_atoms_method.atoms.depth_profile.MovedBlocks`,
    shared by the sets of a column's atoms); a GPU reads them again in each batch.  On 150 atoms of
    an fcc lattice both give the same profile, significance and precision to float64's rounding."""
    from gaussian_atoms_method.atoms import evidence

    read, moved = _fcc_evidence_inputs()
    tabled = evidence.atom_evidence(*read, moved_pulls=moved, device="cpu")
    monkeypatch.setattr(evidence, "moved_blocks_of", lambda *a, **k: None)
    batched = evidence.atom_evidence(*read, moved_pulls=moved, device="cpu")
    assert np.isfinite(tabled.depth_profile).mean() > 0.9
    scale = np.nanmax(np.abs(batched.depth_profile))
    np.testing.assert_allclose(tabled.depth_profile, batched.depth_profile, rtol=1e-9, atol=1e-11 * scale)
    np.testing.assert_allclose(tabled.position_std_A, batched.position_std_A, rtol=1e-12)
    np.testing.assert_array_equal(tabled.depth_open, batched.depth_open)


@pytest.mark.parametrize("with_population", [False, True], ids=["free", "population"])
@pytest.mark.parametrize("tabled", [True, False], ids=["host table", "read in each batch"])
def test_the_depth_profile_through_the_sets_inverse_is_each_system_solved_whole(monkeypatch, tabled, with_population):
    """:func:`~gaussian_atoms_method.atoms.depth_profile.depth_rises` re-fits each moved set
    through the set's inverse information (the still atoms' rows a Schur complement of the moved
    ones'); its float64 reference builds and solves every (5k, 5k) system whole
    (``tests/depth_rises_reference.py``).  On the fcc lattice, where 220 of the 900 moves carry a
    neighbour along (a column), the two agree to 1e-9 of the profile's scale: the same subtraction of cost rises in
    another order, and nothing else.  So too with the population's prior on every width and
    amplitude (atoms/population.py), added to both systems."""
    from depth_rises_reference import depth_rises_reference

    from gaussian_atoms_method.atoms import evidence
    from gaussian_atoms_method.atoms.population import population_precision

    read, moved = _fcc_evidence_inputs()
    population = population_precision(read[1], read[2], np.diag([0.05, 0.1]) ** 2) if with_population else None
    if not tabled:
        monkeypatch.setattr(evidence, "moved_blocks_of", lambda *a, **k: None)
    fast = evidence.atom_evidence(*read, moved_pulls=moved, device="cpu", population=population)
    # the reference: the arguments up to the table, and the prior (no covariance, no sight)
    monkeypatch.setattr(evidence, "depth_rises", lambda *a: depth_rises_reference(*a[:13], prior=a[15]))
    whole = evidence.atom_evidence(*read, moved_pulls=moved, device="cpu", population=population)
    columns = np.isfinite(whole.depth_profile).mean()
    assert columns > 0.9
    scale = np.nanmax(np.abs(whole.depth_profile))
    np.testing.assert_allclose(fast.depth_profile, whole.depth_profile, rtol=1e-9, atol=1e-9 * scale)
    np.testing.assert_array_equal(fast.depth_open, whole.depth_open)
    np.testing.assert_allclose(fast.depth_halfwidth_A, whole.depth_halfwidth_A, rtol=1e-12)


ONE_ATOM = np.array([[0.2, -0.1, 0.3, 0.5, 1.3]])
"""x, y, z (Å), sigma (Å), q of one atom alone in five views (-60 to 60 deg)."""
NOISE = 0.03


def _one_atom_covariance() -> np.ndarray:
    """(5, 5) the inverse of the pixel sum of the products of autograd's derivatives of
    :data:`ONE_ATOM`'s images by (x, y, z, sigma, q), times the noise variance: its Cramer-Rao
    bound (float64)."""
    axes = detector_axes_from_tilts(np.linspace(-60, 60, 5))
    jac = torch.autograd.functional.jacobian(
        lambda p: _render(p, axes), torch.tensor(ONE_ATOM), vectorize=True, strategy="forward-mode"
    )
    flat = jac.reshape(-1, 5)
    return NOISE**2 * np.linalg.inv((flat.T @ flat).numpy())


def _one_atom_evidence():
    axes = detector_axes_from_tilts(np.linspace(-60, 60, 5))
    return atom_evidence(ONE_ATOM[:, :3], ONE_ATOM[:, 3], ONE_ATOM[:, 4], axes, PIXEL_A, NOISE)


def test_the_width_precision_is_the_pixel_sums_cramer_rao_bound():
    """One atom alone in five views under white noise of standard deviation s: its width's
    precision is ``s sqrt([F^-1]_sigma,sigma)``, F the pixel sum of the products of autograd's
    derivatives of its images by (x, y, z, sigma, q) (float64; the closed form agrees with the
    pixel sum far below 1e-9 at 2.5 px widths)."""
    direct = np.sqrt(_one_atom_covariance()[3, 3])
    assert _one_atom_evidence().width_std_A[0] == pytest.approx(direct, rel=1e-6)


def test_the_mass_precision_is_the_pixel_sums_cramer_rao_bound_of_log_q_sigma_cubed():
    """The same atom: the precision of its log mass ``log q + 3 log sigma`` (the mass ``q (2 pi
    sigma^2)^(3/2)``) is ``sqrt(g^T C g)``, ``g = (0, 0, 0, 3 / sigma, 1 / q)``, C the same bound."""
    g = np.array([0.0, 0.0, 0.0, 3.0 / ONE_ATOM[0, 3], 1.0 / ONE_ATOM[0, 4]])
    direct = np.sqrt(g @ _one_atom_covariance() @ g)
    assert _one_atom_evidence().log_mass_std[0] == pytest.approx(direct, rel=1e-6)


def test_a_neighbour_whose_image_overlaps_leaves_an_atoms_mass_less_certain():
    """The same atom alone and with a neighbour 1.2 Å away along the beam of the middle view (its
    image there on the atom's): the neighbour's mass and width can take up part of the atom's, so
    the atom's mass, both re-fitted, is known less well (three times, 0.0077 against 0.0026 here);
    6 Å away along the tilt axis, twelve widths apart in every view, it changes nothing (1e-6)."""
    axes = detector_axes_from_tilts(np.linspace(-60, 60, 5))
    atom = np.array([0.0, 0.0, 0.0, 0.5, 1.3])

    def mass_std(neighbour_A=None):
        p = np.array([atom, [*neighbour_A, 0.5, 1.3]]) if neighbour_A is not None else atom[None]
        return atom_evidence(p[:, :3], p[:, 3], p[:, 4], axes, PIXEL_A, 0.03).log_mass_std[0]

    alone = mass_std()
    assert mass_std([0.0, 0.0, 1.2]) > 2.0 * alone
    assert mass_std([0.0, 6.0, 0.0]) == pytest.approx(alone, rel=1e-6)


def test_an_atom_wider_than_its_elements_width_or_open_in_element_counts_as_open():
    """Widths read against each element's own median (Ni atoms 0.60 Å, Pt 0.55 Å), precisions of
    0.02 Å, a proof level of 4: a Ni atom 0.75 Å wide (7.5 precisions above Ni's width) and a Pt
    atom 0.66 Å wide (5.5 above Pt's; 3 above the median of all) are wider than one atom.  The
    scores count such an atom open, as one whose element is open."""
    from gaussian_atoms_method.atoms.atom_set import AtomSet
    from gaussian_atoms_method.atoms.calibration import wider_than_one_atom
    from gaussian_atoms_method.atoms.evidence import evidence_scores

    species = np.array(["Ni"] * 11 + ["Pt"] * 11)
    sigmas = np.r_[np.full(10, 0.60), 0.75, np.full(10, 0.55), 0.66]
    std = np.full(22, 0.02)
    wide = wider_than_one_atom(sigmas, std, 4.0, species)
    assert np.flatnonzero(wide).tolist() == [10, 21]
    assert np.flatnonzero(wider_than_one_atom(sigmas, std, 4.0)).tolist() == [10]  # one median: 0.60
    positions = np.c_[np.arange(22) * 5.0, np.zeros((22, 2))]
    confidence = np.ones(22)
    confidence[3] = 0.6
    atoms = AtomSet(positions, sigmas, species=species, proven=np.ones(22), depth_open=np.zeros(22),
                    width_open=wide, element_confidence=confidence)  # fmt: skip
    truth = AtomSet(np.delete(positions, [3, 10, 21], axis=0))  # the open three are false atoms
    scores = evidence_scores(atoms, truth)
    assert scores["open_share_of_false"] == 1.0 and scores["proven_found"] == 1.0


def test_the_trust_sentence_counts_each_reason_and_trusts_what_none_leaves_open():
    """Six atoms: one trusted; one not proven and open in depth; one open in depth; one wider than
    one atom; one open in element; one whose element the masses could not tell (NaN): the
    sentence trusts 1 of 6 and counts each reason once per atom it opens."""
    from gaussian_atoms_method.atoms.atom_set import AtomSet
    from gaussian_atoms_method.atoms.trust import open_atoms, trust_words

    atoms = AtomSet(
        np.zeros((6, 3)),
        species=["Ni", "Pt", "Ni", "Pt", "Ni", "Pt"],
        info={"proof_level": 3.9},
        significance=np.full(6, 10.0),
        proven=[1, 0, 1, 1, 1, 1],
        depth_open=[0, 1, 1, 0, 0, 0],
        width_open=[0, 0, 0, 1, 0, 0],
        element_confidence=[1.0, 1.0, 0.99, 1.0, 0.6, np.nan],
    )
    assert open_atoms(atoms).tolist() == [False, True, True, True, True, True]
    words = trust_words(atoms)
    assert words.startswith("trust 1 of 6 atoms") and "element sure" in words
    for said in ("1 not proven", "2 open in depth", "1 wider than one atom", "2 open in element"):
        assert said in words


def test_the_evidence_scores_split_the_atoms_into_open_and_the_rest_alike():
    """Four atoms on true ones (one proven but open in depth, one not proven), two false (one
    open, one proven and closed), one true atom missed with an open atom 1.2 Å away: the atoms
    not called open are two on a true one and one false (2 / 3 found); of the two false atoms one
    is open; of the one miss, one has an open atom within twice the radius; an atom proven but
    open in depth counts as open on both sides."""
    from gaussian_atoms_method.atoms.atom_set import AtomSet
    from gaussian_atoms_method.atoms.evidence import evidence_scores

    truth = np.array([[0, 0, 0], [5, 0, 0], [10, 0, 0], [15, 0, 0], [20, 0, 0]], dtype=np.float64)
    pred = np.array([[0, 0, 0.1], [5, 0, 0.1], [10, 0, 0.1], [15, 0, 0.1], [30, 0, 0], [40, 0, 0], [21.2, 0, 0]])
    proven = np.array([1, 1, 1, 0, 1, 0, 1])
    depth_open = np.array([0, 0, 1, 0, 0, 0, 1])
    atoms = AtomSet(positions=pred, proven=proven, depth_open=depth_open)
    s = evidence_scores(atoms, AtomSet(positions=truth), radius_A=0.75)
    assert (s["proven"], s["open"], s["depth_open"]) == (5, 2, 2)
    assert s["proven_found"] == pytest.approx(2 / 3)
    assert s["trusted_share_of_truth"] == pytest.approx(2 / 5)  # the true atoms at 0 and 5 Å
    # false: the atoms at 30 (proven, closed), 40 (open) and 21.2 (open in depth, 1.2 Å from its truth)
    assert s["open_share_of_false"] == pytest.approx(2 / 3)
    assert s["open_share_of_misses"] == pytest.approx(1.0)
    assert s["open_share_of_disagreement"] == pytest.approx(3 / 4)


def test_a_region_cut_from_a_whole_scores_only_its_own_atoms_each_matched_to_the_whole():
    """A region x <= 10 Å of a row of true atoms 5 Å apart.  The atom at 9.98 Å lies just inside
    on its true atom at 10.1 (outside): matched, so not false; the true atom at 9.95 (inside, a
    row beside) is found by one at 10.03 (outside): not missed.  Cut to the region first, both would be
    disagreement; with the counted masks the closed atoms in the region all lie on a true atom
    and nothing is false or missed."""
    from gaussian_atoms_method.atoms.atom_set import AtomSet
    from gaussian_atoms_method.atoms.evidence import evidence_scores

    truth = np.array([[0.0, 0, 0], [5, 0, 0], [10.1, 0, 0], [9.95, 5, 0], [15, 0, 0]])
    pred = np.array([[0.0, 0, 0.1], [5, 0, 0.1], [9.98, 0, 0], [10.03, 5, 0], [15, 0, 0.1]])
    atoms = AtomSet(positions=pred, proven=np.ones(5, int), depth_open=np.zeros(5, int))
    region = lambda p: p[:, 0] <= 10.0  # noqa: E731
    cut = evidence_scores(atoms.subset(region(pred)), AtomSet(positions=truth[region(truth)]))
    assert cut["proven_found"] == pytest.approx(2 / 3) and cut["open_share_of_misses"] == 0.0
    whole = evidence_scores(atoms, AtomSet(positions=truth), 0.75, False, region(pred), region(truth))
    assert whole["proven_found"] == 1.0 and whole["proven"] == 3
    assert whole["open_share_of_false"] is None and whole["open_share_of_misses"] is None
