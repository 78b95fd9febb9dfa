"""Batched symmetric positive definite solves (physics/spd.py): the evidence's systems, solved
by Cholesky rather than torch's threaded batched LU."""

import os
import subprocess
import sys
import textwrap

import numpy as np
import torch

from gaussian_atoms_method.physics.spd import spd_inverse, spd_solve


def _spd(rng, shape, n):
    a = rng.normal(size=(*shape, n, n))
    return a @ np.swapaxes(a, -1, -2) + n * np.eye(n)


def test_spd_solves_and_inverses_equal_numpys_in_float64():
    """Batches of two dimensions, right-hand sides broadcast: the float64 solutions agree with
    numpy's LU to 1e-12 of their scale (matrices conditioned within 10 of one)."""
    rng = np.random.default_rng(0)
    a = _spd(rng, (3, 4), 12)
    b = rng.normal(size=(4, 12, 2))  # broadcast over the first batch dimension
    solved = spd_solve(torch.from_numpy(a), torch.from_numpy(b)).numpy()
    reference = np.linalg.solve(a, np.broadcast_to(b, (3, 4, 12, 2)))
    assert solved.shape == (3, 4, 12, 2)
    assert np.allclose(solved, reference, rtol=0, atol=1e-12 * np.abs(reference).max())
    inverse = spd_inverse(torch.from_numpy(a)).numpy()
    assert np.allclose(inverse, np.linalg.inv(a), rtol=0, atol=1e-12 * np.abs(inverse).max())


def test_a_matrix_cholesky_cannot_factor_is_solved_by_lu_alone():
    """One member of the batch symmetric but indefinite (not an information matrix, but what
    rounding can leave of a nearly singular one): its solution is LU's, the others' Cholesky's."""
    rng = np.random.default_rng(1)
    a = _spd(rng, (5,), 6)
    a[2] = np.diag([3.0, -1.0, 2.0, 1.0, 5.0, 4.0]) + 0.1
    b = rng.normal(size=(5, 6, 1))
    solved = spd_solve(torch.from_numpy(a), torch.from_numpy(b)).numpy()
    assert np.allclose(solved, np.linalg.solve(a, b), rtol=1e-12, atol=1e-12)
    assert np.allclose(spd_inverse(torch.from_numpy(a)).numpy(), np.linalg.inv(a), rtol=1e-10, atol=1e-12)


def test_batched_solves_finish_and_are_right_after_the_caller_sets_torchs_threads():
    """After ``torch.set_num_threads(2)`` torch's batched LU of 150 x 150 matrices hung or
    reported 'Parameter 6 was incorrect on entry to DLASWP' on this CPU (pytorch issue 141358);
    these solves, in a process of their own, finish and stay right to 1e-8."""
    script = textwrap.dedent(
        """
        import numpy as np, torch
        from gaussian_atoms_method.physics.spd import spd_inverse, spd_solve
        torch.set_num_threads(2)
        rng = np.random.default_rng(0)
        for _ in range(20):
            a = rng.normal(size=(120, 150, 150))
            a = torch.from_numpy(a @ a.transpose(0, 2, 1) + 150 * np.eye(150))
            eye = torch.eye(150, dtype=a.dtype)
            assert (a @ spd_inverse(a) - eye).abs().max() < 1e-8
            assert (a @ spd_solve(a, eye.expand(120, 150, 150)) - eye).abs().max() < 1e-8
        print("done")
        """
    )
    environ = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300, env=environ)
    assert result.returncode == 0 and result.stdout.strip() == "done", result.stderr[-2000:]
    assert "DLASWP" not in result.stderr
