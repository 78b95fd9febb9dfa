"""A tilt axis at an angle in the image (``tilt_axis_angle_deg``), as IMOD and SerialEM report it.

The recorded images are the ideal ones (axis along the detector columns for tilt_axis "y")
turned in the image plane; the check is independent of our projector's conventions:
scipy.ndimage.rotate turns the ideal projections, and the cameras the dataparser builds must
render the true atoms onto the turned images."""

import numpy as np
import pytest
import torch
from scipy import ndimage

from dataparsers.tilt_series_dataparser import TiltSeriesDataParserConfig
from dataparsers.tilt_series_format import load_tilt_series, write_tilt_series
from gaussian_atoms_method.atoms.atom_set import AtomSet
from gaussian_atoms_method.atoms.candidates import backprojection_candidates
from gaussian_atoms_method.atoms.matching import score_atoms
from gaussian_atoms_method.harness.simulate import project_gaussian_potential, spherical_particle
from gaussian_atoms_method.nerfstudio_layer.model import GaussianAtomsModelConfig
from gaussian_atoms_method.physics.geometry import imod_axis_angle

ANGLE_DEG = -86.0  # a value IMOD reports for real series


@pytest.fixture(scope="module")
def turned_series(tmp_path_factory):
    sphere = spherical_particle("Au", 7.0)
    # A lopsided piece of the sphere: a centred fcc sphere looks the same turned by 180 deg, so
    # -86 and +86 deg (172 deg apart) could not be told apart.
    keep = (sphere.positions[:, 0] + 0.6 * sphere.positions[:, 1] > -1.0) & (sphere.positions[:, 1] > -3.0)
    atoms = AtomSet(sphere.positions[keep], species=[sphere.species[i] for i in np.flatnonzero(keep)])
    angles = np.arange(-60.0, 61.0, 10.0)
    ideal = project_gaussian_potential(atoms, angles, 0.3, 64)
    # scipy turns by +a from rows towards columns; the recorded image is turned by -a.
    turned = np.stack([ndimage.rotate(p, -ANGLE_DEG, reshape=False, order=3) for p in ideal])
    out = write_tilt_series(
        tmp_path_factory.mktemp("turned"), turned, angles, 0.3, truth=atoms, tilt_axis_angle_deg=ANGLE_DEG
    )
    return out, atoms, turned


def test_cameras_render_the_true_atoms_onto_the_turned_images(turned_series):
    out, atoms, turned = turned_series
    outputs = TiltSeriesDataParserConfig(data=out).setup().get_dataparser_outputs("train")
    model = GaussianAtomsModelConfig(num_random=len(atoms), init="random", coarse_steps=0).setup(
        scene_box=outputs.scene_box, num_train_data=len(turned), metadata=outputs.metadata
    )
    norm = outputs.metadata["normalisation"]
    with torch.no_grad():  # the true atoms as the model's Gaussians (0.35 Å atoms, unit mass scale)
        model.gauss_params["means"].copy_(torch.as_tensor(norm.positions_from_A(atoms.positions), dtype=torch.float32))
        model.gauss_params["log_sigmas"].fill_(float(np.log(0.35 * norm.length_scale)))
    model.eval()
    inner = (slice(12, 52), slice(12, 52))  # away from the corners the turn leaves empty
    for v in (0, 6, 12):
        image = model.get_outputs(outputs.cameras[v : v + 1])["projection"][..., 0].detach().numpy()
        corr = np.corrcoef(image[inner].ravel(), turned[v][inner].ravel())[0, 1]
        # Measured 1.0000 (cubic interpolation of 0.35 Å-wide atoms on 0.3 Å pixels
        # loses little); the turn in the wrong sense correlates 0.04-0.07.
        assert corr > 0.99, (v, corr)


def test_backprojection_start_finds_every_atom_in_the_turned_series(turned_series):
    out, atoms, _ = turned_series
    series = load_tilt_series(out)
    assert series.tilt_axis_angle_deg == ANGLE_DEG
    args = (series.projections, series.angles_deg, series.pixel_size_A, series.tilt_axis, series.centre_px)
    found = backprojection_candidates(*args, max_count=2 * len(atoms), tilt_axis_angle_deg=ANGLE_DEG)
    assert score_atoms(found[: len(atoms)], atoms.positions)["tpr"] == 1.0
    # Ignoring the angle puts the slices across the axis: most atoms are missed.
    blind = backprojection_candidates(*args, max_count=2 * len(atoms))
    assert score_atoms(blind[: len(atoms)], atoms.positions)["tpr"] < 0.5


def test_mrc_header_of_imod_gives_the_angle(tmp_path):
    import mrcfile

    data = np.random.default_rng(1).uniform(size=(3, 8, 9)).astype(np.float32)
    with mrcfile.new(tmp_path / "tilt.mrc") as mrc:
        mrc.set_data(data)
        mrc.voxel_size = 0.42
        mrc.add_label("newstack: Tilt axis angle = -86.3, binning = 1  spacing = 2.8")
    (tmp_path / "tilt.tlt").write_text("-20.0\n0.0\n20.0\n")
    series = load_tilt_series(tmp_path, "tilt.mrc", "tilt.tlt")
    # IMOD measures from Y, the rows: our tilt axis "x" at the same angle.
    assert series.tilt_axis == "x" and series.tilt_axis_angle_deg == pytest.approx(-86.3)
    as_y = load_tilt_series(tmp_path, "tilt.mrc", "tilt.tlt", tilt_axis="y")
    assert as_y.tilt_axis_angle_deg == pytest.approx(imod_axis_angle(-86.3, "y")) == pytest.approx(3.7)
    given = load_tilt_series(tmp_path, "tilt.mrc", "tilt.tlt", tilt_axis_angle_deg=5.0)
    assert given.tilt_axis_angle_deg == 5.0  # an option overrides the header
