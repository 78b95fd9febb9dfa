"""Slices of the reconstructed potential with atoms overlaid."""

import numpy as np
import pytest
from PIL import Image

from gaussian_atoms_method.atoms.atom_set import AtomSet
from gaussian_atoms_method.atoms.slices import potential_on_plane, write_slices_png
from gaussian_atoms_method.harness.metrics import voxelise_gaussians


def _atoms(n=40, seed=0):
    rng = np.random.default_rng(seed)
    return AtomSet(rng.uniform(-6, 6, (n, 3)), sigmas=rng.uniform(0.4, 0.8, n), amplitudes=rng.uniform(1, 3, n))


def test_plane_equals_the_central_slice_of_the_voxelised_potential():
    """The separable plane evaluation and the voxel grid sample the same sum of Gaussians
    (voxelise_gaussians cuts each Gaussian at 4 sigma, as the plane does: exp(-8) = 3e-4 of a
    peak is the most they can differ by)."""
    atoms = _atoms()
    n, spacing = 61, 0.25
    volume = voxelise_gaussians(atoms.positions, atoms.sigmas, atoms.amplitudes, spacing, (n, n, n))
    coords = (np.arange(n) - (n - 1) / 2) * spacing
    for normal, u, v, sl in (
        (2, 0, 1, volume[:, :, n // 2]),
        (1, 0, 2, volume[:, n // 2, :]),
        (0, 1, 2, volume[n // 2]),
    ):
        plane = potential_on_plane(atoms, normal, 0.0, u, v, coords, coords)
        np.testing.assert_allclose(plane, sl, atol=3.5e-4 * atoms.amplitudes.max() * 4)


def test_slices_png_is_written_complete(tmp_path):
    pred, truth = _atoms(), _atoms()
    path = write_slices_png(pred, tmp_path / "slices.png", truth, title="test")
    image = Image.open(path)
    assert image.format == "PNG" and image.size[0] > image.size[1] > 300
    assert not list(tmp_path.glob(".slices*"))  # no temporary file left
    with pytest.raises(ValueError, match="sigma_A"):
        write_slices_png(AtomSet(np.zeros((2, 3))), tmp_path / "x.png")


def test_dose_figure_reads_ours_and_the_peer_and_draws(tmp_path):
    """scripts/studies/dose_figure.py: the benchmark-peer CSV gives ours and the peer (doses ascending),
    the benchmark-accuracy CSV one series per method; the figure is written."""
    import importlib.util
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "scripts" / "studies" / "dose_figure.py"
    spec = importlib.util.spec_from_file_location("dose_figure", script)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    peer = tmp_path / "peer.csv"
    peer.write_text(
        "dose,n_true,n_pred,n_matched,tpr,fp_per_true_atom,rmsd_pm,seconds,peer_n_pred,peer_n_matched,peer_tpr,peer_fp_per_true_atom,peer_rmsd_pm\n"
        "1.6e5,208,208,208,1.0,0.0,3.3,25,208,208,1.0,0.0,4.2\n"
        "8e3,208,210,208,1.0,0.0096,20.1,25,199,199,0.9567,0.0,28.8\n"
    )
    au = tmp_path / "au.csv"
    au.write_text(
        "particle,atoms,tilts,noise_std,peak_to_noise,method,tpr,fp_per_true_atom,rmsd_pm,ssim,n_pred,seconds,machine\n"
        "au,857,limited,80.0,8.9,ours,1.0,0.0,5.0,0.6,857,40,x\n"
        "au,857,limited,20.0,4.5,ours,1.0,0.007,10.9,0.6,863,38,x\n"
        "au,857,limited,20.0,4.5,sart,0.897,0.24,41.1,0.6,975,18,x\n"
    )
    series = module.peer_series(module.read_rows(peer))
    assert series["ours"][0] == [8e3, 1.6e5] and series["peer"][1]["tpr"] == [0.9567, 1.0]
    methods = module.method_series(module.read_rows(au))
    assert methods["ours"][0] == [20.0, 80.0] and methods["ours"][1]["rmsd_pm"] == [10.9, 5.0]
    assert set(methods) == {"ours", "sart"}
    out = tmp_path / "dose.png"
    subprocess.run(
        [sys.executable, str(script), "--peer", str(peer), "--au", str(au), "--output", str(out)],
        check=True,
        capture_output=True,
    )
    assert out.stat().st_size > 10_000
