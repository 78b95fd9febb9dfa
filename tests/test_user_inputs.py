"""What a new user trips on: a file given as --data, angles passed as values, files others can
read, and one-line errors naming the option."""

import os
import stat

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
        xyz = write_atoms(AtomSet(np.zeros((2, 3)) + [[0, 0, 0], [2.5, 0, 0]], species=["Au", "Au"]), tmp_path / "atoms.xyz")
        png = write_rdf_png(np.linspace(0.05, 8, 160), np.ones(160), 1.5, 0.0, tmp_path / "rdf.png")
    finally:
        os.umask(old)
    for path in (xyz, png):
        assert stat.S_IMODE(os.stat(path).st_mode) == 0o644
