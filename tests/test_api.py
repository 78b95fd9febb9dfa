"""The Python API: arrays (or a HyperSpy signal) in, atoms out, through the CLI's engine."""

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

import gaussian_atoms_method as ga
from gaussian_atoms_method.atoms.matching import score_atoms
from gaussian_atoms_method.harness.input_cases import BROKEN
from gaussian_atoms_method.harness.simulate import simulate_tilt_series, spherical_particle

BIN = Path(sys.executable).parent


@pytest.fixture(scope="module")
def particle():
    """A 43-atom Au sphere, the model's own physics (Gaussian atoms and blur), 15 tilts,
    peak-to-noise near 36: every atom 2.9 Å from its neighbours against a 0.61 Å blur."""
    truth = spherical_particle("Au", radius_A=5.0)
    angles = np.arange(-70.0, 71.0, 10.0)
    sim = simulate_tilt_series(truth, angles, potential="gaussian", noise_std=20.0, seed=0)
    return truth, angles, sim.projections


def test_reconstruct_arrays_gives_the_atoms(particle, capfd):
    truth, angles, projections = particle
    atoms = ga.reconstruct(projections, angles, 0.25, device="cpu", max_num_iterations=400, progress=False)
    said, drawn = capfd.readouterr()
    assert "%|" not in said + drawn  # progress=False: no bar, the evidence's and the final refit's neither
    # a run that keeps no files names none (its working directory is gone when the call returns)
    assert "atoms returned (no files kept" in said and "atoms.xyz" not in said, said
    assert "pixels of 0.25 Å (from the pixel_size_A argument)" in said
    scores = score_atoms(atoms.positions, truth.positions)
    # As the end-to-end CLI test: the model's physics, well-separated atoms, high SNR: all found,
    # none invented, positions far below the 0.25 Å pixel (noise-limited precision is ~1 pm).
    assert scores["tpr"] == 1.0 and scores["fp_per_true_atom"] == 0.0 and scores["rmsd_pm"] < 5.0
    assert atoms.sigmas.shape == atoms.amplitudes.shape == (len(atoms),)
    assert atoms.position_std_A.shape == (len(atoms), 3) and np.all(
        (atoms.position_std_A > 1e-3) & (atoms.position_std_A < 0.05)
    )
    assert np.all(atoms.atom_class >= 1)  # every reported atom has a class; non-atoms are apart
    assert len(atoms.info["non_atoms"]) == 0


def test_reconstruct_imports_no_nerfstudio_and_keeps_a_run_the_viewer_reads(tmp_path):
    """The engine runs the fit from the arrays in memory: neither nerfstudio nor torchvision is
    imported; a kept run's config.yml builds the config nerfstudio's tools read (its data: the
    copy kept beside the run)."""
    code = (
        "import sys, numpy as np, gaussian_atoms_method as ga\n"
        "from gaussian_atoms_method.harness.simulate import simulate_tilt_series, spherical_particle\n"
        "truth = spherical_particle('Au', radius_A=5.0); angles = np.arange(-70.0, 71.0, 10.0)\n"
        "sim = simulate_tilt_series(truth, angles, potential='gaussian', noise_std=20.0, seed=0)\n"
        f"atoms = ga.reconstruct(sim.projections, angles, 0.25, device='cpu', max_num_iterations=30, progress=False, "
        f"output_dir={str(tmp_path)!r})\n"
        "print('found', sorted({m.split('.')[0] for m in sys.modules} & {'nerfstudio', 'torchvision', 'gsplat'}))\n"
        "print(atoms.info['run_dir'])\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    out = run.strip().split("\n")[-2:]  # after the run's own lines
    assert out[0] == "found []", run
    import yaml

    config = yaml.load((Path(out[1]) / "config.yml").read_text(), Loader=yaml.Loader)
    assert type(config).__name__ == "GaussianAtomsTrainerConfig" and config.max_num_iterations == 30
    series = config.pipeline.datamanager.dataparser.data
    assert (series / "tilt_series.json").is_file() and series.parent == tmp_path / "reconstruct" / "tilt_series"
    assert config.get_base_dir() == Path(out[1]) and list(Path(out[1]).glob("nerfstudio_models/step-*.ckpt"))


def test_reconstruct_leaves_torch_and_the_interpreter_as_it_found_them():
    """A notebook that calls the API keeps its own process: after ``ga.reconstruct`` torch's
    functions and optimisers' methods, tyro's ``cli`` and nerfstudio's ``torch_compile`` are
    the objects they were (torch's own caches aside), the interpreter's switch
    interval and recursion limit, torch's threads, default dtype and TF32 flags and numpy's huge-page
    request (a launcher's own process turns it off) are unchanged,
    and every module it brought into ``sys.modules`` is a module that was imported (no stand-in
    put there).  Run in a fresh interpreter: the launchers, which may shorten their own start,
    are not imported."""
    code = textwrap.dedent(
        """
        import sys, types
        import numpy as np, torch, torch._refs, tyro
        import nerfstudio.utils.misc as misc

        def ours(fn):  # whether a layer of a wrapped function is ours (torch wraps a step with its hooks)
            layers = []
            while fn is not None:
                layers.append(str(getattr(fn, "__module__", "")).startswith("gaussian_atoms"))
                fn = getattr(fn, "__wrapped__", None)
            return any(layers)

        def state():
            # each method, and whether what it runs once torch's compiler is loaded is ours
            # (torch caches its own there on first use)
            methods = {}
            for name, fn in vars(torch.optim.Optimizer).items():
                cached = getattr(getattr(fn, "__wrapped__", None), "__dynamo_disable", None)
                methods[name] = (id(fn), str(getattr(cached, "__module__", "")).startswith("gaussian_atoms"))
            return (
                id(torch._refs._broadcast_shapes), id(torch.broadcast_shapes), methods, ours(torch.optim.Adam.step),
                id(tyro.cli), id(misc.torch_compile), sys.getswitchinterval(),
                sys.getrecursionlimit(), torch.get_num_threads(), torch.get_default_dtype(),
                torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32,
                np._core.multiarray._get_madvise_hugepage(),
            )

        before, modules = state(), set(sys.modules)
        import gaussian_atoms_method as ga
        from gaussian_atoms_method.harness.simulate import simulate_tilt_series, spherical_particle

        angles = np.arange(-70.0, 71.0, 10.0)
        sim = simulate_tilt_series(spherical_particle("Au", radius_A=5.0), angles, potential="gaussian", noise_std=20.0)
        atoms = ga.reconstruct(sim.projections, angles, 0.25, device="cpu", max_num_iterations=30, progress=False)
        assert len(atoms) > 0
        stand_ins = sorted(
            k
            for k in set(sys.modules) - modules
            if not isinstance(sys.modules[k], types.ModuleType)
            or type(sys.modules[k]).__module__.startswith("gaussian_atoms")
        )
        changed = [i for i, (b, a) in enumerate(zip(before, state())) if b != a]
        print("changed", changed, "stand-ins", stand_ins)
        """
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.strip().split("\n")[-1] == "changed [] stand-ins []", run.stdout[-2000:]


@pytest.mark.parametrize("origin_A", [(0.0, 0.0, 0.0), (3.0, -2.0, 1.0)])
def test_a_given_start_keeps_what_the_data_hold_and_drops_the_rest(particle, tmp_path, origin_A):
    """``start_atoms``: the true atoms moved 0.3 Å at random, and one more in the vacuum 6 Å
    beyond the particle's surface.  The fit returns every atom to within the precision of the
    first test and drops the vacuum one (no mass there in any view).  The start is read in the
    frame ``atoms.xyz`` is written in, the series' ``origin_A`` at its tilt centre (it had been
    read about the tilt centre: a start off by the origin)."""
    from dataparsers.tilt_series_format import TiltSeries
    from gaussian_atoms_method.atoms.atom_set import AtomSet, write_atoms

    truth, angles, projections = particle
    origin = np.asarray(origin_A)
    rng = np.random.default_rng(1)
    moved = truth.positions + rng.normal(scale=0.3 / np.sqrt(3), size=truth.positions.shape)
    start = np.vstack([moved, [[0.0, 0.0, 11.0]]]) + origin
    path = write_atoms(AtomSet(positions=start, species=np.array(["Au"] * len(start))), tmp_path / "start.xyz")
    series = TiltSeries(projections.astype(np.float32), angles, 0.25, origin_A=origin)
    atoms = ga.reconstruct(series, device="cpu", max_num_iterations=400, progress=False, start_atoms=path)
    scores = score_atoms(atoms.positions - origin, truth.positions)
    assert scores["tpr"] == 1.0 and scores["fp_per_true_atom"] == 0.0 and scores["rmsd_pm"] < 5.0


def test_a_replica_floor_widens_each_stated_precision(particle, capfd):
    """``precision_floor_A`` (read on a replica by ``evaluate``) is added in quadrature: without it
    this particle's atoms are stated to 1-50 pm (the test above), with a floor of 10/20/30 pm each
    statement lies between the floor and the quadrature sum with 5 pm, and the run says so."""
    truth, angles, projections = particle
    floor = (0.1, 0.2, 0.3)
    atoms = ga.reconstruct(
        projections, angles, 0.25, device="cpu", max_num_iterations=400, progress=False, precision_floor_A=floor
    )
    said = capfd.readouterr().out
    assert "with the floor given, 10.0/20.0/30.0 pm in quadrature" in said, said
    std = atoms.position_std_A
    assert np.all(std >= np.array(floor)) and np.all(std <= np.sqrt(np.array(floor) ** 2 + 0.05**2))
    assert np.all(atoms.depth_halfwidth_A >= 1.96 * 0.3)


def test_a_run_scores_itself_only_on_the_truth_inside_the_field_it_reports(particle, tmp_path):
    """A truth wider than the field (a film's whole model against one sub-area) is scored where
    the run reports atoms: 20 true atoms 60 Å off the 43-atom particle (beyond the detector's
    6.5 Å half-width at every tilt) neither lower the TPR nor are matched, and the run says how
    many it left out."""
    from dataparsers.tilt_series_format import load_tilt_series, write_tilt_series
    from gaussian_atoms_method.atoms.atom_set import AtomSet

    truth, angles, projections = particle
    far = truth.positions[:20] + np.array([60.0, 0.0, 0.0])
    wide = AtomSet(np.r_[truth.positions, far], species=np.full(len(truth) + 20, "Au"))
    series = load_tilt_series(write_tilt_series(tmp_path / "series", projections, angles, 0.25, truth=wide))
    atoms = ga.reconstruct(series, device="cpu", max_num_iterations=400, progress=False, output_dir=tmp_path / "run")
    scores = json.loads((Path(atoms.info["run_dir"]) / "evaluation.json").read_text())
    assert scores["n_true"] == len(truth) and scores["n_true_uncounted"] == 20
    assert scores["tpr"] == 1.0 and scores["fp_per_true_atom"] == 0.0


def test_reconstruct_reads_the_kernel_then_holds_it(particle):
    """``psf="held-out"`` through the API: the reading pass, then the atoms with the kernel held
    (the trainer's two passes); the model's own physics has no tails to read, so the atoms come
    out as with the defaults: all found, none invented."""
    truth, angles, projections = particle
    atoms = ga.reconstruct(
        projections,
        angles,
        0.25,
        device="cpu",
        max_num_iterations=400,
        progress=False,
        psf="held-out",
        stop_split_at=300,
    )
    scores = score_atoms(atoms.positions, truth.positions)
    assert scores["tpr"] == 1.0 and scores["fp_per_true_atom"] == 0.0 and scores["rmsd_pm"] < 5.0


def test_reconstruct_takes_a_hyperspy_signal(particle, tmp_path):
    """A Signal2D with its tilt axis in degrees and its image axes in nm: the same atoms as the
    arrays (the same trainer, seed and data on the CPU), and the run kept where asked."""
    hs = pytest.importorskip("hyperspy.api")
    truth, angles, projections = particle
    signal = hs.signals.Signal2D(projections)
    tilt = signal.axes_manager[0]
    tilt.units, tilt.scale, tilt.offset = "deg", 10.0, -70.0
    for axis in signal.axes_manager.signal_axes:
        axis.units, axis.scale = "nm", 0.025
    atoms = ga.reconstruct(signal, device="cpu", max_num_iterations=400, progress=False, output_dir=tmp_path)
    scores = score_atoms(atoms.positions, truth.positions)
    assert scores["tpr"] == 1.0 and scores["fp_per_true_atom"] == 0.0 and scores["rmsd_pm"] < 5.0
    run = atoms.info["run_dir"]
    assert (run / "config.yml").is_file() and (run / "atoms.xyz").is_file()


def test_a_kept_run_loads_back_as_the_viewer_loads_it(particle, tmp_path):
    """With ``output_dir`` the run's config.yml names data that are kept beside it, so the run
    loads back as ``ns-viewer`` and ``gaussian-atoms view`` load it, with the Gaussians whose
    atoms were written (to the 1e-8 Å the file keeps).  Under umask 022 everything written, the
    kept tilt series' directory too, is readable by a colleague on the same machine."""
    import os
    import stat

    from gaussian_atoms_method.nerfstudio_layer.launch import load_model

    truth, angles, projections = particle
    mask = os.umask(0o022)
    try:
        atoms = ga.reconstruct(
            projections, angles, 0.25, device="cpu", max_num_iterations=300, progress=False, output_dir=tmp_path
        )
    finally:
        os.umask(mask)
    unreadable = [p for p in tmp_path.rglob("*") if stat.S_IMODE(p.stat().st_mode) & 0o044 != 0o044]
    assert not unreadable
    model = load_model(atoms.info["run_dir"] / "config.yml")
    gaussians = model.atoms().positions
    nearest = np.min(np.linalg.norm(atoms.positions[:, None] - gaussians[None], axis=-1), axis=1)
    assert len(gaussians) >= len(atoms) and np.all(nearest < 1e-6)


def test_bad_input_raises_the_cli_line(tmp_path):
    """The message of InputError is the line the CLI prints for the same series."""
    data = BROKEN["single projection"][0](tmp_path / "series")
    cli = subprocess.run(
        [
            str(BIN / "gaussian-atoms"),
            "train",
            "--machine.device-type",
            "cpu",
            "--output-dir",
            str(tmp_path / "out"),
            "tilt-series",
            "--data",
            str(data),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert cli.returncode == 2
    with pytest.raises(ga.InputError) as info:
        ga.read_tilt_series(data)
    assert str(info.value) == cli.stderr.strip().splitlines()[-1]
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    "call, fragment",
    [
        (
            lambda p, a: ga.reconstruct(p[:1], a[:1], 0.25),
            "projections: 1 projection from 1 direction: at least 3 are needed",
        ),
        (lambda p, a: ga.reconstruct(p, a[:3], 0.25), "3 tilt angles for 15 projections"),
        (lambda p, a: ga.reconstruct(p, a), "pixel_size_A: the pixel size is missing"),
        (lambda p, a: ga.reconstruct(p, a, 0.25, merge_treshold_A=0.7), "merge_treshold_A: not a model option"),
        (lambda p, a: ga.reconstruct(p, a, 0.25, device="tpu"), "device must be one of"),
    ],
)
def test_bad_arguments_are_one_line(particle, call, fragment):
    _, angles, projections = particle
    with pytest.raises(ga.InputError, match="^gaussian-atoms: error: ") as info:
        call(projections, angles)
    assert fragment in str(info.value) and "\n" not in str(info.value)


def test_the_views_held_out_turn_shifts_and_gains_on_for_a_misregistered_series(particle, capfd, tmp_path):
    """``decide_registration``: the views moved by shifts 1.4 px RMS (no translation of the
    particle among them) and scaled by gains 7% RMS (the Ta film's scatter): a fit of the even
    views with per-view shifts (and gains, or not: 7% against the noise of 8 held-out views is
    for the views to judge) predicts the odd ones better than one without, so the run learns
    them (config.yml records the choice, registration.csv the shifts and gains learned) and finds
    every atom; the series with no misregistration is the other test's (all found without them)."""
    import torch
    from scipy import ndimage

    from dataparsers.registration_file import read_registration
    from gaussian_atoms_method.atoms.view_prediction import gauge_free_shifts
    from gaussian_atoms_method.physics.geometry import detector_axes_from_tilts

    truth, angles, projections = particle
    rng = np.random.default_rng(11)
    axes = torch.as_tensor(detector_axes_from_tilts(angles)[:, :2])
    shifts_px = gauge_free_shifts(torch.as_tensor(rng.normal(0.0, 1.0, (len(angles), 2))), axes).numpy()
    gains = np.exp(rng.normal(0.0, 0.07, len(angles)))
    moved = np.stack([g * ndimage.shift(p, s, order=3) for p, s, g in zip(projections, shifts_px, gains)])
    atoms = ga.reconstruct(
        moved.astype(np.float32),
        angles,
        0.25,
        device="cpu",
        max_num_iterations=400,
        progress=False,
        decide_registration=True,
        output_dir=tmp_path,
    )
    said = capfd.readouterr().out
    line = next(x for x in said.splitlines() if "per-view registration:" in x)
    chosen = line.split("per-view registration: ")[1].split(" (")[0]
    assert chosen in ("shifts", "shifts and gains") and all(
        f"RMS with {name}" in said for name in ("shifts", "gains", "shifts and gains")
    ), said
    config = (atoms.info["run_dir"] / "config.yml").read_text()
    assert "refine_alignment: true" in config and f"refine_gain: {str(chosen != 'shifts').lower()}" in config
    scores = score_atoms(atoms.positions, truth.positions)
    assert scores["tpr"] == 1.0 and scores["fp_per_true_atom"] == 0.0
    # registration.csv: the learned shifts are the applied ones (the content's displacement, as
    # ndimage.shift made it) to a tenth of a pixel, against 1.4 px RMS: a view's shift is fixed by
    # all its atoms together, each placed to a small fraction of a pixel at this noise (0.02 px read)
    learned, learned_gains = read_registration(atoms.info["run_dir"] / "registration.csv")
    assert "the views' learned registration: shifts" in said and "--shifts-from registration.csv" in said
    # the API returns them too, from memory (the file keeps six significant digits)
    np.testing.assert_allclose(atoms.info["view_shifts_px"], learned, rtol=1e-5)
    assert np.sqrt(np.mean((learned - shifts_px) ** 2)) < 0.1
    # the gains against their geometric mean (a gain common to all views is the atoms'): where
    # learned, RMS within 2%, under a third of their 7% scatter (0.9% read, up to 2.2% in one
    # view: the amplitudes and gains trade within the noise); else each 1
    expected = gains / np.exp(np.log(gains).mean()) if chosen != "shifts" else np.ones(len(gains))
    assert np.sqrt(np.mean((learned_gains - expected) ** 2)) < 0.02


def test_the_same_input_gives_the_same_atoms_and_evidence_bit_for_bit_on_a_cpu(particle):
    """Two runs of one series on a CPU, the caller's global generators in two states: every atom,
    its evidence and the run's own floor equal to the bit (the start found in a thread, the views'
    pulls read by two workers, the pictures drawn by child processes, the own replica's refit: none
    may leave its order in the result, and no draw is from the caller's generators).  Real
    sub-areas 23 and 25 of the Ta film gave identical atoms in two runs on this CPU and on an H200
    (docs/performance.md)."""
    import random

    import torch

    _, angles, projections = particle
    runs = []
    for seed in (0, 1):  # the caller's global generators, in another state each time: the fit draws from its own
        random.seed(seed), np.random.seed(seed), torch.manual_seed(seed)
        options = dict(species="Au", device="cpu", max_num_iterations=200, progress=False)
        runs.append(ga.reconstruct(projections, angles, 0.25, **options))
    assert len(runs[0]) > 0
    for name in ("positions", "sigmas", "amplitudes", "position_std_A", "significance", "depth_halfwidth_A"):
        np.testing.assert_array_equal(getattr(runs[0], name), getattr(runs[1], name), err_msg=name)
    np.testing.assert_array_equal(runs[0].trusted, runs[1].trusted)
    assert runs[0].info.get("precision_floor_A") == runs[1].info.get("precision_floor_A")


def _children() -> set[int]:
    """The process ids of this process's children, from every thread's (Linux's /proc)."""
    import os

    tasks = Path(f"/proc/{os.getpid()}/task")
    return {int(c) for t in tasks.iterdir() for c in (t / "children").read_text().split()}


def test_reconstruct_leaves_the_callers_generators_threads_and_children_as_it_found_them(particle):
    """The fit draws from its own generators only, and leaves Python's, NumPy's and torch's
    global ones as they were: the caller's next draws are the ones it would have made without
    the call.  No thread or child process it started outlives it."""
    import random
    import threading

    import torch

    _, angles, projections = particle
    random.seed(7), np.random.seed(7), torch.manual_seed(7)
    before = random.getstate(), np.random.get_state(), torch.get_rng_state()
    expected = random.random(), float(np.random.rand()), float(torch.rand(1))
    random.setstate(before[0]), np.random.set_state(before[1]), torch.set_rng_state(before[2])
    threads, children = set(threading.enumerate()), _children()
    ga.reconstruct(projections, angles, 0.25, device="cpu", max_num_iterations=30, progress=False)
    assert random.getstate() == before[0] and torch.equal(torch.get_rng_state(), before[2])
    after = np.random.get_state()
    assert after[0] == before[1][0] and np.array_equal(after[1], before[1][1]) and after[2:] == before[1][2:]
    assert (random.random(), float(np.random.rand()), float(torch.rand(1))) == expected
    assert set(threading.enumerate()) <= threads and _children() <= children
