"""The fit's options (``--pipeline.model.*`` on the command line, keyword arguments of
:func:`gaussian_atoms_method.reconstruct`): what each does and where its value comes from.

:class:`FitOptions` holds them all, with no nerfstudio import; the nerfstudio method's config
(:class:`gaussian_atoms_method.nerfstudio_layer.options.GaussianAtomsOptions`) is splatfacto's
config with these in place of its own.  The density control's settings are declared once, in
:class:`~gaussian_atoms_method.density.settings.DensitySettings`, which this class extends.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional, Tuple, Union

from gaussian_atoms_method.density.settings import DensitySettings
from gaussian_atoms_method.engine.errors import OptionError


def field_docs(cls) -> dict[str, str]:
    """Each field of dataclass ``cls`` (and of its dataclass bases) with the string that follows
    it in the class body, read from the source with :mod:`ast` (a string right after a field is
    its documentation, as tyro and Sphinx take it)."""
    import ast
    import inspect
    import textwrap

    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass) or klass.__module__ == "builtins":
            continue
        try:
            tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        except (OSError, TypeError, SyntaxError):
            continue
        body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
        for node, after in zip(body, body[1:]):
            if (
                isinstance(node, ast.AnnAssign)
                and isinstance(node.target, ast.Name)
                and isinstance(after, ast.Expr)
                and isinstance(after.value, ast.Constant)
                and isinstance(after.value.value, str)
            ):
                docs[node.target.id] = after.value.value
    return docs


@dataclass
class UserFirstOptions:
    """The options a user sets first: the data's background and probe, a film, the alignment,
    the data term, the start, when to stop, the seed.  The first base of
    :class:`FitOptions`, so that ``--help`` lists them first."""

    background: Literal["auto", "none", "constant", "plane", "smooth"] = "auto"
    """A per-projection background fitted with the atoms (carbon support, contamination, a
    detector offset, a phase image's floor): a constant, a plane over the detector, or
    ``smooth``: each view's floor starting as its outer frame shows it (the frame's least-squares
    quadratic surface, :func:`gaussian_atoms_method.physics.detector_floor.frame_surfaces`) with a
    constant and quadratic correction (a frame the object reaches holds its tails).  Each is
    solved in closed form on the pixels the Gaussians leave empty, each time its view is
    rendered, and shared by all views while their fits agree (:mod:`gaussian_atoms_method.engine.floors`).  ``auto``:
    when the projections' outer frame sits significantly off zero (more than 5 standard errors
    of its mean, :func:`gaussian_atoms_method.physics.detector_floor.detector_floor`: the peer's aSi-208
    counts sit on 1.0 count), a constant if the frame is flat and ``smooth``
    if it is flat about its quadratic surface (within 1.5 times the noise variance at its level
    either way); where atoms reach the frame, the same read from the frame pixels they leave
    alone (:func:`gaussian_atoms_method.physics.detector_floor.clipped_frame`)."""
    psf: Literal["learned", "held-out", "fixed", "none"] = "learned"
    """The microscope's point-spread function: ``learned``, a radially symmetric kernel of unit
    integral shared by every view (Gaussians of 1, 2 and 4 Å weighted by learned weights,
    :mod:`gaussian_atoms_method.physics.psf`) convolves the projections, so a probe's tails and
    rings are not explained by extra faint, wide Gaussians; ``fixed``: the kernel of
    ``psf_weights``, held (a probe measured, or chosen on held-out views with
    ``gaussian-atoms held-out-views``); ``held-out``: a first pass reads the kernel on the odd views
    while the atoms learn from the even ones, then the run starts again with it held
    (:mod:`gaussian_atoms_method.engine.kernel_reading`: learned with the atoms, a probe's tails can go to extra
    Gaussians
    instead; twice the time; where half the views fit poorly the reading is too wide: a dense
    54,000-atom particle without tails read 53% at 2 Å); ``none``: the blur is in the atoms' widths alone (the
    paper's model)."""
    psf_weights: Tuple[float, float, float] = (0.0, 0.0, 0.0)
    """The kernel's intensity fractions in its Gaussians of 1, 2 and 4 Å (the rest in the delta,
    that is in the atoms' own widths): held with ``psf fixed``, the start with ``psf learned``."""
    extended_object: Literal["auto", "on", "off"] = "auto"
    """An object wider than the field of view (a film): Gaussians also fill the slab beyond the
    detector across the tilt axis, as far as the rays that reach the detector travel, so the
    high-tilt views' material outside the box is explained there, and only the Gaussians above
    the detector are reported as atoms (the rest go to ``non_atoms.xyz``).  ``auto``: when the
    views' projected mass grows like 1/cos(tilt)
    (:func:`gaussian_atoms_method.physics.field_of_view.film_evidence`, 3 standard errors)."""
    refine_alignment: bool = False
    """Learn a per-projection in-plane shift with the atoms (residual misalignment of the tilt
    series).  The shifts a translation of the object makes (each view's detector axes times one
    3D vector) are taken out (:func:`~gaussian_atoms_method.atoms.view_prediction.gauge_free_shifts`):
    they move the atoms, not the views, and left in they let the particle drift along the beam."""
    refine_gain: bool = False
    """Learn a per-projection gain with the atoms: each view's atoms' projection times
    ``exp(g_v - mean(g))`` (the beam current or the detector drifting between views; 6.8% RMS
    between the Ta film's views).  The mean is taken out: a gain common to every view is the
    atoms' amplitudes' scale (:func:`~gaussian_atoms_method.engine.rendering.view_gain`)."""
    decide_registration: bool = False
    """Let the views a fit did not see decide ``refine_alignment`` and ``refine_gain``: the even
    views are fitted without per-view registration, with shifts, with gains and with both, each
    fit predicts the odd views (each after its own best shift and gain: a held-out view's
    registration is no fit's), and the run learns what predicts them best
    (:func:`~gaussian_atoms_method.engine.run.choose_registration`).  Five fits' time (four on half the
    views)."""
    refine_tilts: bool = False
    """Learn a per-projection tilt-angle offset (about the tilt axis) with the atoms: errors of
    the goniometer readings.  Offsets are taken relative to their mean (a common offset is the
    same as rotating the particle).  Single-axis tilt series only."""
    loss: Literal["auto", "l1", "l2", "huber", "poisson"] = "auto"
    """Data term (:mod:`gaussian_atoms_method.physics.data_terms`): ``auto`` reads the noise
    from the projections before training (:func:`gaussian_atoms_method.physics.noise.noise_from_projections`)
    and takes the Poisson likelihood where the variance grows significantly with the signal
    (electron counts), else Huber's (least squares within 1.345 noise standard deviations,
    L1 beyond: additive noise, robust to the model's misfit); or force ``l1`` (the paper's),
    ``l2``, ``huber`` or ``poisson``.  Every run prints the noise it read and the term it chose."""
    init: Literal["backprojection", "random"] = "backprojection"
    """Where the Gaussians start: at the strongest local maxima of a smoothed filtered
    back-projection (see :mod:`gaussian_atoms_method.atoms.initialise`), or at random positions (the
    paper).  Back-projection needs single-axis tilts; otherwise random is used."""
    start_atoms: Optional[Path] = None
    """Start from these atoms instead (any atom file :func:`~gaussian_atoms_method.atoms.atom_set.read_atoms`
    reads; positions in Å in the series' frame, as ``atoms.xyz`` writes them): refine a model
    traced elsewhere, or ask whether the data hold it (the fit moves off what they do not)."""
    stop_when_converged: bool = True
    """End training early once the atoms are settled: over a refine interval at most
    false_discovery_rate of the atoms' worth of Gaussians added or removed, and the RMS step of the others
    (matched within merge_threshold_A) below ``converged_fraction`` of the atoms' noise-limited
    precision (:mod:`gaussian_atoms_method.atoms.uncertainty`), at two checks in a row
    (:mod:`gaussian_atoms_method.engine.convergence`).  Further steps would move the atoms by less than the data can
    tell
    apart.  Until then the run acts on what the checks show (:mod:`gaussian_atoms_method.engine.stopping`): the final
    merges
    and prune once only the set still churns, a halved position rate while the positions only
    scatter."""
    seed: int = 0
    """Seed of the random initialisation and duplications."""


@dataclass
class FitOptions(DensitySettings, UserFirstOptions):
    """Gaussian atoms: isotropic 3D Gaussians fitted to a tilt series.

    The options a user sets first come first (:class:`UserFirstOptions`), then the density
    control's (:class:`~gaussian_atoms_method.density.settings.DensitySettings`, declared there
    once); the fit's own settings follow."""

    init_mass: Literal["backprojection", "equal"] = "backprojection"
    """How the measured mass is shared among the starting Gaussians: in proportion to the
    smoothed back-projection at each (noise candidates start faint and are pruned sooner;
    back-projection start only), or equally."""
    num_random: int = 10000
    """Number of Gaussians of a random start (``init random``, the paper's).  The
    back-projection start takes as many candidates as the data hold above their noise
    (:mod:`gaussian_atoms_method.atoms.initialise`): no cap."""
    init_sigma_A: float = 0.7
    """Initial width of every Gaussian, Å."""
    init_extent: float = 0.8
    """Side of the cube (normalised units, the detector's longer side is 1) that the random
    Gaussians start in."""
    judge_after_fit: bool = True
    """The final merges and prune judge significance in what the fit leaves unexplained, as an
    atom sees it (the residuals' variance times their correlation over an atom), never less
    than the noise read before training (:func:`gaussian_atoms_method.engine.noise_reading.noise_after_fit`).  Where
    the data
    match the forward model that is the noise and nothing changes; on real data the fit's
    leftover structure is otherwise read as significant atoms and resolved pairs."""
    final_refit: bool = True
    """After the final prune and merge, when they removed anything, one pass over the views so the
    survivors take up what the removed Gaussians carried (:mod:`gaussian_atoms_method.engine.refit`)."""
    second_look: bool = True
    """Once the fit has converged, where the residuals prove more than half an atom (neighbours
    re-fitted) at significantly more of the places an atom could be (at least the hard core from
    every Gaussian, inside the material) than they prove less than minus half a one, fit again
    from the start with a Gaussian added at every such place with positive mass
    (:mod:`gaussian_atoms_method.engine.second_look`: a light atom whose bonded neighbours took
    up its mass leaves a residual under any search's level).  Only with a hard core (``--species``,
    or read); up to twice the time where it runs.  7,000 carbon atoms in phase images at 2,000
    e/Å²: found 0.931 -> 0.994."""
    evidence: bool = True
    """Each atom with its evidence in atoms.xyz/atoms.csv: its significance, proven or open, its
    depth interval and its precision with its neighbours re-fitted, from the views' own residuals
    (:mod:`gaussian_atoms_method.atoms.evidence`; its cost: docs/performance.md).  Off: the
    isolated atom's Cramér-Rao bound alone."""
    precision_floor_A: Tuple[float, float, float] = field(default_factory=lambda: tuple([0.0] * 3))
    """An error along x, y, z (Å) that the views' own scatter cannot show, added in quadrature to
    each atom's stated precision and depth interval: a bias alike in every view (a probe's tails
    over a neighbour, an atom's shape).  Read it from a replica of the experiment: ``evaluate`` of
    a fit of ``gaussian-atoms simulate --like`` reports ``precision_floor_A``
    (:mod:`gaussian_atoms_method.atoms.calibration`).  Zero: the views' own statement.  (A new tuple
    each time: the compiler makes every ``(0.0, 0.0, 0.0)`` literal of a module one object,
    ``psf_weights``' too, and config.yml would write the two as one YAML anchor.)"""
    own_floor: bool = True
    """Read that floor in the run itself where no floor is given: the run's atoms drawn again
    through the views' contrast (Lobato's potentials, a probe read from the views) with its
    registration and noise, refitted from where they stand until their passes no longer drift,
    their errors beside the precision stated (:mod:`gaussian_atoms_method.engine.own_floor`; its
    cost: docs/performance.md).  Atoms of no element given are drawn as
    :data:`~gaussian_atoms_method.engine.own_floor.STAND_IN_ELEMENT`'s.  False: the views' scatter
    alone is stated."""
    projector: Literal["auto", "tiled", "dense", "gsplat"] = "auto"
    """Projection backend (all exact to float32; their speeds: docs/performance.md): ``dense``,
    the full-image separable matmul (the fastest on a GPU); ``tiled``, each Gaussian only on the
    tiles it reaches (the fastest on a CPU); ``gsplat``, tiled with stock gsplat's tile
    intersection (CUDA only).  ``auto``: dense on CUDA, tiled on CPU."""
    coarse_steps: int = 300
    """Coarse to fine: the first this many steps fit the projections binned 2 x 2 (a quarter of
    the pixels to evaluate), then full resolution.  0: always full resolution.  300 covers the
    warm-up and the first prune, where the atoms are found and the noise candidates go, with the
    same final result (docs/performance.md, skips)."""
    position_rate_px: Optional[float] = 0.2887
    """Adam's rate for the positions at the start, in detector pixels (the optimiser's
    configured rate for ``means`` is rescaled to it; its schedule's tenfold decay is kept).  A
    start on the back-projection's voxels (the detector's pixels) is off by up to half a voxel
    per axis: a uniform error of standard deviation 1/sqrt(12) = 0.2887 voxel, about what
    Adam's first steps move.  In pixels, the rate in Å does not grow with the field of view (a
    rate normalised by the detector's side is twice as large in Å on a detector twice as wide,
    where the positions then settle later).  None: the configured rate as it is."""
    converged_fraction: float = 1.0
    """See stop_when_converged."""
    views_per_step: Union[int, Literal["auto"]] = "auto"
    """Training views fitted per step: the view nerfstudio hands the model and this many minus
    one others drawn at random, rendered in one projector call, one loss over all.  On a GPU a
    batch of views costs about one view's kernel launches and the averaged gradient is smoother
    (docs/performance.md: several views per step); on a CPU each view costs its own time.
    ``auto``: on a GPU as many as fit (:func:`gaussian_atoms_method.engine.step_views.auto_views_per_step`: at most 8,
    within half the free GPU memory by the projector's measured bytes per Gaussian and view; never
    by time, so one input takes one number of views), else 1;
    1 with refine-alignment, refine-tilts or anisotropic Gaussians (per-view parameters), which
    a number above 1 cannot be combined with."""
    cuda_graphs: bool = True
    """On a CUDA GPU, capture a training step's tensor work (the projection, the floors, the
    loss and its gradients) once as a CUDA graph and replay it each step, captured again when the
    Gaussians change (:mod:`.step_graph`): at 20,000 atoms and more a step is bound by the
    host's dispatch of its ~300 small operations, not by the GPU.  False: every operation
    dispatched from Python, as nerfstudio does (the same arithmetic)."""
    snapshot_every: int = 0
    """Every this many steps (0: never) write the current atoms to ``snapshots/`` in the run
    directory with the wall-clock time, for time-to-accuracy benchmarks: the Gaussians the run
    would report as atoms were it stopped there (in the field of view and the support, as
    ``atoms.xyz``), before the final merges and prune."""

    def per_view_options(self) -> list[str]:
        """The options on that give each view its own parameters (one view per step only)."""
        return [
            name
            for name, on in (
                ("refine-alignment", self.refine_alignment),
                ("refine-gain", self.refine_gain),
                ("refine-tilts", self.refine_tilts),
                ("isotropic False", not self.isotropic),
            )
            if on
        ]

    def check(self) -> None:
        """Raise :class:`OptionError` naming the option for settings that cannot work together,
        before anything is built (the model checks what needs the data when it is built)."""
        if self.views_per_step != "auto" and not (isinstance(self.views_per_step, int) and self.views_per_step >= 1):
            raise OptionError(f"--pipeline.model.views-per-step must be auto or at least 1, got {self.views_per_step}")
        if self.views_per_step != "auto" and self.views_per_step > 1:
            per_view = self.per_view_options()
            if per_view:
                raise OptionError(
                    f"--pipeline.model.views-per-step {self.views_per_step} cannot be combined with "
                    f"--pipeline.model.{per_view[0]} (per-view parameters); use 1"
                )
        positive = {
            "num-random": self.num_random,
            "init-sigma-A": self.init_sigma_A,
            "min-sigma-A": self.min_sigma_A,
            "max-sigma-A": self.max_sigma_A,
            "refine-every": self.refine_every,
            "merge-every": self.merge_every,
            "max-gaussians": self.max_gaussians,
        }
        for name, value in positive.items():
            if not value > 0:
                raise OptionError(f"--pipeline.model.{name} must be positive, got {value}")
        if not self.min_sigma_A <= self.init_sigma_A <= self.max_sigma_A:
            raise OptionError(
                f"--pipeline.model.init-sigma-A {self.init_sigma_A} must lie within [min-sigma-A {self.min_sigma_A}, "
                f"max-sigma-A {self.max_sigma_A}]"
            )
        if not 0 < self.false_alarm_rate < 1:
            raise OptionError(f"--pipeline.model.false-alarm-rate must lie in (0, 1), got {self.false_alarm_rate}")
        if self.position_rate_px is not None and not self.position_rate_px > 0:
            raise OptionError(
                f"--pipeline.model.position-rate-px must be positive (detector pixels per step) or None, got "
                f"{self.position_rate_px}"
            )
        if not 0 < self.false_discovery_rate < 1:
            raise OptionError(
                f"--pipeline.model.false-discovery-rate must lie in (0, 1), got {self.false_discovery_rate}"
            )
        if self.start_atoms is not None:
            from gaussian_atoms_method.atoms.atom_set import AtomFileError, read_atoms

            try:
                if len(read_atoms(self.start_atoms)) == 0:
                    raise AtomFileError(f"{self.start_atoms}: holds no atoms")
            except AtomFileError as error:
                raise OptionError(f"--pipeline.model.start-atoms: {error}") from None
        from gaussian_atoms_method.physics.psf import KERNEL_WIDTHS_A

        if len(self.precision_floor_A) != 3 or not all(math.isfinite(f) and f >= 0 for f in self.precision_floor_A):
            raise OptionError(
                "--pipeline.model.precision-floor-A must be three non-negative lengths in Å (x y z), got "
                f"{' '.join(f'{f:g}' for f in self.precision_floor_A)}"
            )
        if len(self.psf_weights) != len(KERNEL_WIDTHS_A) or min(self.psf_weights) < 0 or sum(self.psf_weights) >= 1:
            raise OptionError(
                f"--pipeline.model.psf-weights takes {len(KERNEL_WIDTHS_A)} non-negative fractions (at "
                f"{', '.join(f'{w:g}' for w in KERNEL_WIDTHS_A)} Å) summing to less than 1, got "
                f"{' '.join(f'{w:g}' for w in self.psf_weights)}"
            )
        if (
            self.merge_threshold_A < 0
            or self.prune_mass_fraction < 0
            or self.coarse_steps < 0
            or self.snapshot_every < 0
        ):
            raise OptionError(
                "--pipeline.model.merge-threshold-A, prune-mass-fraction, coarse-steps and snapshot-every must not be "
                "negative"
            )
