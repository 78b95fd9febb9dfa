"""Every supported file format: write a small file with its own library, read it back."""

import h5py
import mrcfile
import numpy as np
import pytest
import scipy.io
import tifffile

from dataparsers.readers import read_angles, read_stack
from dataparsers.tilt_series_format import TiltSeriesError, load_tilt_series

STACK = np.random.default_rng(0).normal(size=(4, 6, 5)).astype(np.float32)  # (N, H, W)
ANGLES = np.array([-60.0, -20.0, 20.0, 60.0])


def test_npy_npz(tmp_path):
    np.save(tmp_path / "s.npy", STACK)
    np.testing.assert_array_equal(read_stack(tmp_path / "s.npy").projections, STACK)
    np.savez(tmp_path / "s.npz", projections=STACK, other=STACK[:, :, :2])
    np.testing.assert_array_equal(read_stack(tmp_path / "s.npz", dataset="projections").projections, STACK)
    with pytest.raises(TiltSeriesError, match="holds 2 arrays.*name the one"):
        read_stack(tmp_path / "s.npz")


def test_tiff_stack(tmp_path):
    tifffile.imwrite(tmp_path / "s.tif", STACK)
    np.testing.assert_array_equal(read_stack(tmp_path / "s.tif").projections, STACK)


def test_mrc_with_pixel_size_and_imod_tlt(tmp_path):
    with mrcfile.new(tmp_path / "s.mrc") as mrc:
        mrc.set_data(STACK)
        mrc.voxel_size = 0.25
    got = read_stack(tmp_path / "s.mrc")
    np.testing.assert_array_equal(got.projections, STACK)
    assert got.pixel_size_A == pytest.approx(0.25)
    (tmp_path / "s.tlt").write_text("\n".join(f"{a:.2f}" for a in ANGLES) + "\n")
    np.testing.assert_array_equal(read_angles(tmp_path / "s.tlt"), ANGLES)


def test_emd_tomviz_layout(tmp_path):
    """Berkeley EMD as tomviz writes it: /data/tomography/{data, dim1..3}, angles on one dim."""
    with h5py.File(tmp_path / "s.emd", "w") as f:
        g = f.create_group("data").create_group("tomography")
        g.attrs["emd_group_type"] = 1
        g["data"] = np.moveaxis(STACK, 0, 2)  # (H, W, N) with the angle last
        for i, (name, units, values) in enumerate(
            [("x", "[n_m]", np.arange(6)), ("y", "[n_m]", np.arange(5)), ("angles", "[deg]", ANGLES)]
        ):
            d = g.create_dataset(f"dim{i + 1}", data=values)
            d.attrs["name"], d.attrs["units"] = np.bytes_(name), np.bytes_(units)
    got = read_stack(tmp_path / "s.emd")
    np.testing.assert_array_equal(got.projections, STACK)
    np.testing.assert_array_equal(got.angles_deg, ANGLES)


def test_plain_hdf5(tmp_path):
    with h5py.File(tmp_path / "s.h5", "w") as f:
        f["a/b"] = STACK
    np.testing.assert_array_equal(read_stack(tmp_path / "s.h5").projections, STACK)
    np.testing.assert_array_equal(read_stack(tmp_path / "s.h5", dataset="a/b").projections, STACK)
    with pytest.raises(TiltSeriesError, match="no 3D dataset 'c'"):
        read_stack(tmp_path / "s.h5", dataset="c")


def test_mat_v5_and_v73(tmp_path):
    scipy.io.savemat(
        tmp_path / "s.mat",
        {"Projs": np.moveaxis(STACK, 0, 2), "angles": np.stack([np.zeros(4), ANGLES, np.zeros(4)], 1)},
    )
    np.testing.assert_array_equal(read_stack(tmp_path / "s.mat").projections, STACK)
    np.testing.assert_array_equal(read_angles(tmp_path / "s.mat")[:, 1], ANGLES)
    # v7.3 is HDF5 with MATLAB's column-major layout: a MATLAB (H, W, N) array appears reversed.
    with h5py.File(tmp_path / "v73.mat", "w", userblock_size=512) as f:
        f["Projs"] = np.moveaxis(STACK, 0, 2).transpose()
    with open(tmp_path / "v73.mat", "r+b") as f:  # the header MATLAB writes in the user block
        f.write(
            b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Sun Nov 22 00:00:00 2026 HDF5 schema 1.00 .".ljust(
                116
            )
        )
    np.testing.assert_array_equal(read_stack(tmp_path / "v73.mat").projections, STACK)


def test_peer_data_reads(shared_data):
    got = read_stack(shared_data / "asi208" / "aSi_2nmFosCetr_Dose1p6e5_cov35pm_ForBM3D.mat")
    assert got.projections.shape == (60, 128, 128)
    euler = read_angles(shared_data / "asi208" / "Si_Angle.mat")
    assert euler.shape == (60, 3)
    res = read_stack(shared_data / "resire_convention" / "sample_projections_amorphous.mat")
    assert res.projections.shape == (41, 64, 64)


def test_errors_name_file(tmp_path):
    with pytest.raises(TiltSeriesError, match="missing.mrc: projections file not found"):
        read_stack(tmp_path / "missing.mrc")
    (tmp_path / "bad.mrc").write_bytes(b"not an mrc")
    with pytest.raises(TiltSeriesError, match="bad.mrc: could not read projections"):
        read_stack(tmp_path / "bad.mrc")
    np.save(tmp_path / "flat.npy", STACK[0])
    with pytest.raises(TiltSeriesError, match="flat.npy: the array must be a 3D stack"):
        read_stack(tmp_path / "flat.npy")
    (tmp_path / "a.txt").write_text("1 2\n3 4\n")
    with pytest.raises(TiltSeriesError, match="a.txt: expected N tilt angles or N x 3 Euler"):
        read_angles(tmp_path / "a.txt")


def test_dataparser_reads_matlab_stack_and_euler_angles(tmp_path):
    """A RESIRE-style .mat stack (H, W, N) and N x 3 Euler angles load through the manifest
    and the dataparser options: tilt index moved first, theta taken, centre as given."""
    import scipy.io

    from dataparsers.tilt_series_format import TiltSeriesError, load_tilt_series

    stack = np.random.default_rng(0).uniform(size=(12, 10, 4))
    euler = np.array([[0, -30, 0], [0, -10, 0], [0, 10, 0], [0, 30, 0]], dtype=float)
    scipy.io.savemat(tmp_path / "projs.mat", {"Projs": stack})
    scipy.io.savemat(tmp_path / "angles.mat", {"angles": euler})
    series = load_tilt_series(tmp_path, "projs.mat", "angles.mat", 0.5, centre_px=(6, 5))
    np.testing.assert_allclose(series.projections, np.moveaxis(stack, 2, 0).astype(np.float32))
    np.testing.assert_array_equal(series.angles_deg, [-30, -10, 10, 30])
    np.testing.assert_array_equal(series.centre_px, [6, 5])
    assert series.euler_deg is None  # phi = psi = 0: a single-axis series
    # A 30-degree psi moves the 6 x 5 x 6 Å volume's corners 2.7 Å from the single axis the
    # start back-projects about: more than MAX_START_OFFSET_A, one line naming the file.
    scipy.io.savemat(tmp_path / "bad.mat", {"angles": euler + [[0, 0, 30]] * 4})
    with pytest.raises(TiltSeriesError, match=r"bad\.mat: Euler angles with phi or psi up to 30 deg move"):
        load_tilt_series(tmp_path, "projs.mat", "bad.mat", 0.5)


def test_mrc_pixel_size_and_imod_tlt(tmp_path):
    """An MRC stack with its pixel size in the header and an IMOD .tlt file need no pixel size option."""
    import mrcfile

    from dataparsers.tilt_series_format import load_tilt_series

    data = np.random.default_rng(1).uniform(size=(3, 8, 9)).astype(np.float32)
    with mrcfile.new(tmp_path / "tilt.mrc") as mrc:
        mrc.set_data(data)
        mrc.voxel_size = 0.42
    (tmp_path / "tilt.tlt").write_text("-20.0\n0.0\n20.0\n")
    series = load_tilt_series(tmp_path, "tilt.mrc", "tilt.tlt")
    assert series.pixel_size_A == pytest.approx(0.42, rel=1e-6)
    np.testing.assert_allclose(series.projections, data)


@pytest.mark.parametrize("suffix", [".hspy", ".emd", ".mrc"])
def test_series_written_by_rosettasciio_reads_back(tmp_path, suffix):
    """A tilt series saved by HyperSpy (through rosettasciio) reads back with the same arrays,
    pixel size and angles: from the file's angle axis (hspy, emd), or an IMOD .tlt beside an
    MRC, whose header keeps no angles."""
    hs = pytest.importorskip("hyperspy.api")
    angles = np.array([-60.0, -30.0, 0.0, 30.0])
    signal = hs.signals.Signal2D(STACK.copy())
    tilt, rows, cols = signal.axes_manager[0], signal.axes_manager[1], signal.axes_manager[2]
    tilt.name, tilt.units, tilt.scale, tilt.offset = "tilt", "degrees", 30.0, -60.0
    for axis in (rows, cols):
        axis.units, axis.scale = "nm", 0.03
    signal.save(tmp_path / f"series{suffix}")
    (tmp_path / "series.tlt").write_text("\n".join(f"{a:g}" for a in angles))
    series = load_tilt_series(tmp_path, f"series{suffix}", "series.tlt" if suffix == ".mrc" else None)
    np.testing.assert_array_equal(series.projections, STACK)
    assert series.pixel_size_A == pytest.approx(0.3, rel=1e-6)  # 0.03 nm, stored in float32
    np.testing.assert_allclose(series.angles_deg, angles)


def test_etspy_tilts_and_anisotropic_pixels(tmp_path):
    """Uneven tilts in ``metadata.Tomography.tilts`` (where etspy keeps them) are the angles;
    pixels of different height and width are refused in one line."""
    hs = pytest.importorskip("hyperspy.api")
    uneven = np.array([-62.0, -21.5, 3.0, 57.0])
    signal = hs.signals.Signal2D(STACK.copy())
    signal.metadata.set_item("Tomography.tilts", uneven)
    signal.axes_manager[1].units = signal.axes_manager[2].units = "Å"
    signal.axes_manager[1].scale = signal.axes_manager[2].scale = 0.42
    signal.save(tmp_path / "s.hspy")
    got = read_stack(tmp_path / "s.hspy")
    np.testing.assert_allclose(got.angles_deg, uneven)
    assert got.pixel_size_A == pytest.approx(0.42)
    signal.axes_manager[2].scale = 0.5  # HyperSpy lists the signal axes x then y: this is the rows
    signal.save(tmp_path / "wide.hspy")
    with pytest.raises(TiltSeriesError, match=r"wide.hspy: pixels of 0.5 x 0.42 Å; square pixels expected"):
        read_stack(tmp_path / "wide.hspy")
