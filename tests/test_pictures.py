"""The run's pictures, drawn in this process or by a child process (atoms/picture_process.py)."""

import numpy as np

from gaussian_atoms_method.atoms.atom_set import AtomSet
from gaussian_atoms_method.atoms.picture_process import PictureProcess
from gaussian_atoms_method.atoms.pictures import draw_slices, write_population_png
from gaussian_atoms_method.atoms.slices import slice_planes


def _atoms(n=40, seed=0):
    rng = np.random.default_rng(seed)
    return AtomSet(rng.uniform(-6, 6, (n, 3)), sigmas=rng.uniform(0.4, 0.8, n), amplitudes=rng.uniform(1, 3, n))


def _population(seed=0):
    rng = np.random.default_rng(seed)
    masses, sigmas = np.exp(rng.normal(0, 0.2, 60)), rng.uniform(0.5, 0.8, 60)
    atoms, classes = np.arange(60) < 55, np.where(np.arange(60) < 30, 1, 2)
    return masses, sigmas, atoms, classes, 2, (masses[:5] * 0.1, sigmas[:5])


def test_a_child_draws_the_pictures_this_process_draws(tmp_path):
    """The same arrays give the same PNG bytes in a child as here (matplotlib is deterministic
    for a given figure: no date in its PNG), so handing a picture over changes nothing."""
    planes = slice_planes(_atoms(), _atoms(seed=1))
    children = [PictureProcess(), PictureProcess()]
    assert children[0].draw(draw_slices, planes, tmp_path / "child_slices.png", "test")
    assert children[1].draw(write_population_png, *_population(), tmp_path / "child_classes.png")
    draw_slices(planes, tmp_path / "slices.png", "test")
    write_population_png(*_population(), tmp_path / "classes.png")
    for child in children:
        child.wait()
    assert (tmp_path / "child_slices.png").read_bytes() == (tmp_path / "slices.png").read_bytes()
    assert (tmp_path / "child_classes.png").read_bytes() == (tmp_path / "classes.png").read_bytes()


def test_a_child_that_fails_says_why_and_leaves_no_file(tmp_path):
    """A child's failure is its last line, and no half-written file: the run then draws the
    picture itself (results.write_results), so a child never fails a run."""
    child = PictureProcess()
    assert child.draw(draw_slices, "not planes", tmp_path / "slices.png", "")
    assert not child.wait() and child.error.startswith("AttributeError")
    assert child.picture[0] is draw_slices and not list(tmp_path.iterdir())


def test_a_child_given_no_picture_ends():
    """A run that stops before its pictures ends its children (none is left behind)."""
    children = [PictureProcess(), PictureProcess()]
    for child in children:
        assert not child.wait()  # none was handed a picture: ended, not waited on forever
    assert all(child._process.returncode is not None for child in children)
