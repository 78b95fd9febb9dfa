"""Objects wider than the field of view: the evidence, the slab's reach, and what is reported."""

import json
import math

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from dataparsers.tilt_series_dataparser import TiltSeriesDataParserConfig
from dataparsers.tilt_series_format import write_tilt_series
from gaussian_atoms_method.atoms import picture_process
from gaussian_atoms_method.atoms.atom_set import AtomSet, read_atoms
from gaussian_atoms_method.harness.simulate import project_gaussian_potential, spherical_particle
from gaussian_atoms_method.physics.field_of_view import FILM_Z, film_evidence, slab_half_width

PIXEL_A = 0.4
ANGLES = np.arange(-60.0, 61.0, 6.0)


def _slab(rng, half_width_A=60.0, half_depth_A=4.0, half_length_A=5.0, density_per_A3=0.02) -> AtomSet:
    """Random Au atoms in a slab far wider (x) than a 64-pixel detector (12.8 Å half-width)."""
    n = int(density_per_A3 * 8 * half_width_A * half_depth_A * half_length_A)
    box = np.array([half_width_A, half_length_A, half_depth_A])
    return AtomSet(rng.uniform(-1, 1, (n, 3)) * box, species=np.array(["Au"] * n))


def _project(atoms: AtomSet, rng, noise=1.0, pixels=64) -> np.ndarray:
    clean = project_gaussian_potential(atoms, ANGLES, PIXEL_A, pixels)
    return (clean + noise * rng.standard_normal(clean.shape)).astype(np.float32)


def test_film_evidence_tells_a_slab_from_a_particle():
    """A slab wider than the detector puts material under it in proportion to 1/cos(theta): its
    growth term stands far above the views' scatter and carries most of the zero-tilt mass (not
    all: the slab's atoms are discrete, so the number under the detector fluctuates from view to
    view about the uniform slab's t / cos(theta); 0.82 here).  A particle inside the field keeps its mass at every
    tilt: within a few
    standard errors of no growth."""
    rng = np.random.default_rng(0)
    film = film_evidence(_project(_slab(rng), rng), ANGLES)
    assert film.extended and film.z > 10 * FILM_Z
    assert film.outside_fraction > 0.5
    particle = film_evidence(_project(spherical_particle("Au", radius_A=8.0), rng), ANGLES)
    assert not particle.extended and abs(particle.z) < FILM_Z
    assert not film_evidence(np.ones((2, 8, 8)), np.array([0.0, 30.0])).extended  # too few views to tell


def test_slab_half_width_is_where_the_steepest_rays_travel():
    """x = (u + z sin theta) / cos theta at the edge of the detector and the slab, steepest tilt."""
    assert slab_half_width(10.0, 5.0, np.array([-60.0, 0.0, 45.0])) == pytest.approx(
        (10 + 5 * math.sin(math.pi / 3)) / 0.5
    )
    assert slab_half_width(10.0, 5.0, np.zeros(3)) == pytest.approx(10.0)  # untilted: the detector itself


def test_slab_reports_only_the_gaussians_above_the_detector(tmp_path, monkeypatch):
    """In a slab series the model reads the film from the data, fills the slab beyond the
    detector and reports as atoms only the Gaussians above it: none in atoms.xyz lies beyond the
    detector's half-width across the tilt axis, and the Gaussians beyond it (holding the outer
    film's mass) are written to non_atoms.xyz."""
    from gaussian_atoms_method.nerfstudio_layer.launch import train_views
    from gaussian_atoms_method.nerfstudio_layer.model import GaussianAtomsModelConfig

    rng = np.random.default_rng(1)
    atoms = _slab(rng, half_width_A=40.0, density_per_A3=0.01)
    projections = _project(atoms, rng, noise=0.5)
    write_tilt_series(tmp_path / "series", projections, ANGLES, PIXEL_A, truth=atoms)
    outputs = TiltSeriesDataParserConfig(data=tmp_path / "series").setup().get_dataparser_outputs("train")
    model = GaussianAtomsModelConfig(coarse_steps=0).setup(
        scene_box=outputs.scene_box, num_train_data=len(outputs.image_filenames), metadata=outputs.metadata
    )
    ls = model.normalisation.length_scale
    detector_half_A = 0.5 * 64 * PIXEL_A
    assert model.density.half_extent[0] / ls == pytest.approx(slab_half_width(detector_half_A, 0.5 / ls, ANGLES))
    assert model.field_half_extent[0] / ls == pytest.approx(detector_half_A)
    # Along the tilt axis the volume goes three of the widest atom's widths past the detector
    # (the film goes on there); the field stops at the detector.
    assert model.density.half_extent[1] / ls == pytest.approx(detector_half_A + 3.0 * model.config.max_atom_sigma_A)
    assert model.field_half_extent[1] / ls == pytest.approx(detector_half_A)
    beyond = lambda positions: np.abs(positions[:, 0]) > detector_half_A + 1e-6  # noqa: E731
    assert beyond(model.atoms().positions).sum() > 0  # the start reaches beyond the detector
    targets = [torch.as_tensor(p)[..., None] * model.normalisation.data_scale for p in projections]
    train_views(model, outputs.cameras, targets, steps=60, refine=False)
    # The pictures drawn by child processes, as on a machine with cores to spare (atoms/picture_process.py)
    monkeypatch.setattr(picture_process, "spare_cores", lambda children: True)
    handed, draw = [], picture_process.PictureProcess.draw
    monkeypatch.setattr(
        picture_process.PictureProcess, "draw", lambda self, f, *a: handed.append(f.__name__) or draw(self, f, *a)
    )
    model.write_results(tmp_path / "run")
    assert sorted(handed) == ["draw_slices", "write_population_png", "write_rdf_png"]  # none left to this process
    for picture in ("slices.png", "classes.png", "rdf.png"):
        assert (tmp_path / "run" / picture).stat().st_size > 10_000
    reported = read_atoms(tmp_path / "run" / "atoms.xyz")
    others = read_atoms(tmp_path / "run" / "non_atoms.xyz")
    assert len(reported) > 0 and not beyond(reported.positions).any()
    # nearly all of them across the tilt axis, in the outer film
    assert len(others) > 0 and beyond(others.positions).mean() > 0.9
    # In the field a non-atom is one the classification puts outside the support: never a true atom (none within 0.75 Å)
    in_field = ~(np.abs(others.positions) > detector_half_A - 1e-6).any(axis=1)
    if in_field.any():
        assert cKDTree(atoms.positions).query(others.positions[in_field])[0].min() > 0.75
    # check-precision reads the written run as the run scored itself (the same true atoms counted,
    # those straddling the field's edge whose partner lies beyond it left out): one answer, also
    # where 60 steps matched none of them
    from gaussian_atoms_method.harness.precision_check import precision_of_run

    scored = json.loads((tmp_path / "run" / "evaluation.json").read_text())
    checked = precision_of_run(model, tmp_path / "run")
    assert checked["matched"] == scored["n_matched"]
    stated = scored.get("coverage_95_xyz", [math.nan] * 3)  # none where nothing is matched
    assert checked["coverage_95"].tolist() == pytest.approx(stated, abs=1e-12, nan_ok=True)


def test_particle_inside_the_field_keeps_the_cube(tmp_path):
    """No growth with tilt: the volume stays the cube the detector spans and every Gaussian is
    reported (no non_atoms.xyz); extended-object off is the same, on forces the slab."""
    from gaussian_atoms_method.nerfstudio_layer.model import GaussianAtomsModelConfig

    rng = np.random.default_rng(2)
    atoms = spherical_particle("Au", radius_A=6.0)
    write_tilt_series(tmp_path, _project(atoms, rng, pixels=48), ANGLES, PIXEL_A, truth=atoms)
    outputs = TiltSeriesDataParserConfig(data=tmp_path).setup().get_dataparser_outputs("train")
    for option, wide in (("auto", False), ("off", False), ("on", True)):
        model = GaussianAtomsModelConfig(extended_object=option).setup(
            scene_box=outputs.scene_box, num_train_data=len(outputs.image_filenames), metadata=outputs.metadata
        )
        assert (model.density.half_extent[0] > 0.5) == wide, option
        assert model.field_half_extent == (0.5, 0.5, 0.5)
