"""What a new user trips on: a file given as --data, angles passed as values, files others can
read, and one-line errors naming the option."""

import os
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dataparsers.errors import TiltSeriesError
from dataparsers.tilt_series_format import load_tilt_series
from gaussian_atoms_method.atoms.atom_set import AtomSet, write_atoms
from gaussian_atoms_method.harness.input_cases import valid_series


def test_a_projection_file_is_taken_as_data(tmp_path):
    """``--data stack.npy`` reads the file (its folder's manifest is not needed)."""
    data = valid_series(tmp_path / "series")
    np.save(tmp_path / "stack.npy", np.load(data / "projections.npy"))
    series = load_tilt_series(tmp_path / "stack.npy", angles_deg=np.linspace(-60, 60, 7), pixel_size_A=0.3)
    assert series.projections.shape == (7, 24, 24)
    np.testing.assert_allclose(series.angles_deg, np.linspace(-60, 60, 7))


def test_read_tilt_series_takes_angle_values_and_names_bad_ones(tmp_path):
    import gaussian_atoms_method as ga

    data = valid_series(tmp_path / "series")
    series = ga.read_tilt_series(data / "projections.npy", angles_deg=np.linspace(-60, 60, 7), pixel_size_A=0.3)
    assert series.n_views == 7
    with pytest.raises(ga.InputError, match="angles_deg"):
        ga.read_tilt_series(data / "projections.npy", angles_deg=object(), pixel_size_A=0.3)
    with pytest.raises(ga.InputError, match="read_tilt_series"):
        ga.read_tilt_series(data, not_an_option=1)


def test_a_zero_pixel_size_given_as_an_option_names_the_option(tmp_path):
    data = valid_series(tmp_path / "series")
    with pytest.raises(TiltSeriesError, match=r"^--pixel-size-A: pixel_size_A must be a positive number of Å, got 0$"):
        load_tilt_series(data, pixel_size_A=0.0)


def test_files_written_follow_the_umask(tmp_path):
    """With umask 022 the atoms and the pictures are readable by others (mkstemp's 0600 is not
    what a colleague on a shared machine can read)."""
    from gaussian_atoms_method.atoms.pictures import write_rdf_png

    old = os.umask(0o022)
    try:
        xyz = write_atoms(
            AtomSet(np.zeros((2, 3)) + [[0, 0, 0], [2.5, 0, 0]], species=["Au", "Au"]), tmp_path / "atoms.xyz"
        )
        png = write_rdf_png(np.linspace(0.05, 8, 160), np.ones(160), 1.5, 0.0, tmp_path / "rdf.png")
    finally:
        os.umask(old)
    for path in (xyz, png):
        assert stat.S_IMODE(os.stat(path).st_mode) == 0o644


def test_the_viewer_serves_this_machine_unless_asked(tmp_path):
    from gaussian_atoms_method.cli import parse

    (tmp_path / "config.yml").write_text("method_name: gaussian-atoms\n")
    local = parse(["view", "--load-config", str(tmp_path / "config.yml")]).build()
    assert local.viewer.websocket_host == "127.0.0.1" and local.load_config == tmp_path / "config.yml"
    assert (
        parse(["view", "--load-config", str(tmp_path / "config.yml"), "--host", "0.0.0.0"])
        .build()
        .viewer.websocket_host
        == "0.0.0.0"
    )


def test_export_of_a_one_element_particle_writes_one_element(tmp_path):
    """The export verb on a pure particle's atoms asked for Fe,Pt: one element, and a line saying why."""
    import subprocess
    import sys
    from pathlib import Path

    import ase.io

    rng = np.random.default_rng(4)
    grid = np.stack(np.meshgrid(*[np.arange(6)] * 3, indexing="ij"), -1).reshape(-1, 3) * 2.9
    atoms = AtomSet(
        grid.astype(float),
        sigmas=np.full(len(grid), 0.6),
        amplitudes=30.0 * np.exp(rng.normal(scale=0.08, size=len(grid))),
    )
    write_atoms(atoms, tmp_path / "run" / "atoms.xyz")
    (tmp_path / "run" / "config.yml").write_text("method_name: gaussian-atoms\n")
    out = tmp_path / "out.extxyz"
    proc = subprocess.run(
        [
            str(Path(sys.executable).parent / "gaussian-atoms"),
            "export",
            "--load-config",
            str(tmp_path / "run" / "config.yml"),
            "--output",
            str(out),
            "--species",
            "Fe,Pt",
        ],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 0, proc.stderr
    assert set(ase.io.read(out).get_chemical_symbols()) == {"Pt"}
    assert "separate population" in proc.stderr


@pytest.mark.parametrize(
    "bad, named",
    [
        ({"max_num_iterations": "abc"}, "max_num_iterations"),
        ({"max_num_iterations": 0}, "--max-num-iterations"),
        ({"seed": "x"}, "seed"),
        ({"species": "Xx"}, "unknown element 'Xx'"),
        ({"device": "gpu"}, "device"),
        ({"start_atoms": "no_such_atoms.xyz"}, "--pipeline.model.start-atoms: no_such_atoms.xyz: atom file not found"),
    ],
)
def test_every_bad_argument_of_reconstruct_is_an_input_error_naming_it(bad, named):
    import gaussian_atoms_method as ga

    projections = np.random.default_rng(0).uniform(size=(7, 24, 24)).astype(np.float32)
    with pytest.raises(ga.InputError, match=named):
        ga.reconstruct(projections, np.linspace(-60, 60, 7), 0.3, progress=False, **bad)


def test_the_tool_verbs_name_what_they_cannot_use(tmp_path):
    """held-out-views with a kernel that is not three fractions, check-precision without a run:
    one line naming it, exit 2, before anything runs."""
    from gaussian_atoms_method.harness.input_cases import valid_series

    data = valid_series(tmp_path / "series")
    bad = subprocess.run(
        [
            str(Path(sys.executable).parent / "gaussian-atoms"),
            "held-out-views",
            "--data",
            str(data),
            "--output",
            str(tmp_path / "out"),
            "--kernels",
            "learned",
            "0.1,0.2",
        ],
        capture_output=True,
        text=True,
    )
    assert bad.returncode == 2 and bad.stderr.strip().count("\n") == 0 and "'0.1,0.2'" in bad.stderr
    assert not (tmp_path / "out").exists()
    none = subprocess.run(
        [
            str(Path(sys.executable).parent / "gaussian-atoms"),
            "check-precision",
            "--load-config",
            str(tmp_path / "no" / "config.yml"),
        ],
        capture_output=True,
        text=True,
    )
    assert none.returncode == 2 and "config.yml: run config not found" in none.stderr


@pytest.mark.parametrize("pixel_size_A, words", [(40.0, "wider than any atom's image"), (0.003, "narrower than one")])
def test_a_pixel_size_that_cannot_be_right_is_refused_on_a_small_stack(tmp_path, pixel_size_A, words):
    """11 views of 48 x 48 pixels, too few and too small for an atom's width to be read from them:
    a 40 Å pixel (every atom within one pixel: an atom's image is at most 1 Å wide) and a 0.003 Å
    one (the views 0.14 Å across, narrower than any atom) are refused before a fit, in one line
    naming pixel_size_A, through the API, ``gaussian-atoms train`` and ``ns-train``: a non-zero
    exit, no traceback, no run directory."""
    import gaussian_atoms_method as ga
    from gaussian_atoms_method.harness.input_cases import edit_manifest

    data = edit_manifest(valid_series(tmp_path / "series", shape=(48, 48), n_views=11), pixel_size_A=pixel_size_A)
    projections = np.load(data / "projections.npy")
    with pytest.raises(ga.InputError, match=words) as info:
        ga.reconstruct(projections, np.linspace(-60, 60, 11), pixel_size_A, device="cpu", progress=False)
    assert "pixel_size_A" in str(info.value) and "\n" not in str(info.value)
    bin_dir = Path(sys.executable).parent
    for launcher in ([str(bin_dir / "gaussian-atoms"), "train"], [str(bin_dir / "ns-train"), "gaussian-atoms"]):
        command = launcher + ["--machine.device-type", "cpu", "--vis", "tensorboard", "--output-dir"]
        command += [str(tmp_path / "runs"), "tilt-series", "--data", str(data)]
        result = subprocess.run(command, capture_output=True, text=True, timeout=600)
        assert result.returncode != 0 and "Traceback" not in result.stderr + result.stdout, launcher
        assert words in result.stderr + result.stdout and "pixel_size_A" in result.stderr + result.stdout
        assert not (tmp_path / "runs").exists()


def test_a_series_that_cannot_fix_a_3d_position_is_refused_before_the_fit(tmp_path):
    """Two views (two directions: any two atoms of a slice trade places with the other two corners
    of their parallelogram and project the same; fitted anyway, such a series put 1.19 false atoms
    per true one) are refused in one line through the API, ``gaussian-atoms train`` and
    ``ns-train``, with no traceback and no run directory; so are 11 views spanning 3 degrees
    (atoms 2 Å apart along the beam move by under 0.17 Å between them)."""
    import gaussian_atoms_method as ga

    data = valid_series(tmp_path / "series", shape=(48, 48), n_views=3)
    np.save(data / "projections.npy", np.load(data / "projections.npy")[:2])
    (data / "angles.txt").write_text("-60\n60\n")
    projections = np.load(data / "projections.npy")
    with pytest.raises(ga.InputError, match="from 2 directions: at least 3 are needed") as info:
        ga.reconstruct(projections, np.array([-60.0, 60.0]), 0.3, device="cpu", progress=False)
    assert "\n" not in str(info.value)
    narrow = np.random.default_rng(0).uniform(0, 1, (11, 48, 48))
    with pytest.raises(ga.InputError, match="span only 3 deg"):
        ga.reconstruct(narrow, np.linspace(-1.5, 1.5, 11), 0.3, device="cpu", progress=False)
    bin_dir = Path(sys.executable).parent
    for launcher in ([str(bin_dir / "gaussian-atoms"), "train"], [str(bin_dir / "ns-train"), "gaussian-atoms"]):
        command = launcher + ["--machine.device-type", "cpu", "--vis", "tensorboard", "--output-dir"]
        command += [str(tmp_path / "runs"), "tilt-series", "--data", str(data)]
        result = subprocess.run(command, capture_output=True, text=True, timeout=600)
        said = result.stderr + result.stdout
        assert result.returncode != 0 and "Traceback" not in said, launcher
        assert "at least 3 are needed to fix an atom in 3D" in said, said[-2000:]
        assert not (tmp_path / "runs").exists()
