"""Batched solves of symmetric positive definite systems, by Cholesky.

The evidence's systems (each atom's local information, their Schur complements, a covariance's
corner) are symmetric positive definite.  torch's batched LU on the CPU (``linalg.inv``,
``linalg.solve``) factors a batch's matrices on several threads at once, and MKL's LU is not
safe to call that way once ``torch.set_num_threads`` has been called (pytorch issue 141358: a
grain size of zero for matrices above 14 x 14).  On this 2-core CPU, after
``torch.set_num_threads(2)``, batches of 120 matrices 150 x 150 hung within a minute with
"Intel oneMKL ERROR: Parameter 6 was incorrect on entry to DLASWP"; a film's Ray worker (which
sets its threads) hung in the evidence of Ta sub-area 4.  Cholesky's batched factorisation loops
over the batch on one thread (200 such batches, no error), with half LU's work.  A matrix that
Cholesky cannot factor (not positive definite in floating point) is solved alone by LU: one
matrix, one thread.
"""

from __future__ import annotations

import torch


def spd_solve(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a^-1 b`` for symmetric positive definite ``a`` (..., n, n) and ``b`` (..., n, k),
    batch shapes broadcast as :func:`torch.linalg.solve`'s (module text: why not it).

    >>> a = torch.tensor([[4.0, 2.0], [2.0, 3.0]], dtype=torch.float64)
    >>> spd_solve(a, torch.tensor([[2.0], [1.0]], dtype=torch.float64)).ravel().tolist()
    [0.5, 0.0]
    """
    if a.shape[:-2] != b.shape[:-2]:  # torch.broadcast_shapes costs 0.35 ms a call on this CPU: only where needed
        shape = torch.broadcast_shapes(a.shape[:-2], b.shape[:-2])
        a = a.expand(*shape, *a.shape[-2:])
        b = b.expand(*shape, *b.shape[-2:])
    factor, info = torch.linalg.cholesky_ex(a)
    return _by_lu_where_failed(
        info, torch.cholesky_solve(b, factor), lambda i: torch.linalg.solve(_flat(a)[i], _flat(b)[i])
    )


def spd_inverse(a: torch.Tensor) -> torch.Tensor:
    """The inverse of each symmetric positive definite ``a`` (..., n, n) (:func:`spd_solve`).

    >>> a = torch.tensor([[4.0, 2.0], [2.0, 3.0]], dtype=torch.float64)
    >>> torch.allclose(spd_inverse(a) @ a, torch.eye(2, dtype=torch.float64))
    True
    """
    factor, info = torch.linalg.cholesky_ex(a)
    return _by_lu_where_failed(info, torch.cholesky_inverse(factor), lambda i: torch.linalg.inv(_flat(a)[i]))


def spd_inverse_rows(a: torch.Tensor, rows: int) -> torch.Tensor:
    """The first ``rows`` rows (..., rows, n) of the inverse of each symmetric positive definite
    ``a`` (..., n, n): ``rows`` solves against the factor instead of its whole inverse (an atom's
    own rows of its set's covariance, a twentieth of the work for a set of 21 atoms).

    >>> a = torch.tensor([[4.0, 2.0], [2.0, 3.0]], dtype=torch.float64)
    >>> torch.allclose(spd_inverse_rows(a, 1), spd_inverse(a)[:1])
    True
    """
    unit = torch.eye(a.shape[-1], rows, dtype=a.dtype, device=a.device).expand(*a.shape[:-2], -1, -1)
    return spd_solve(a, unit).transpose(-1, -2)


def _flat(batch: torch.Tensor) -> torch.Tensor:
    """``batch`` (..., n, k) as (B, n, k): read only where a factorisation failed, so that the
    usual call copies nothing (a broadcast batch is copied by it)."""
    return batch.reshape(-1, *batch.shape[-2:])


def _by_lu_where_failed(info: torch.Tensor, out: torch.Tensor, lu) -> torch.Tensor:
    """``out`` (..., n, k) with each matrix Cholesky could not factor (``info`` (...) non-zero:
    not positive definite in floating point) replaced by ``lu(i)``, its LU solve by its flat
    index ``i``: one matrix at a time, so no two LU factorisations run at once."""
    failed = torch.nonzero(info.reshape(-1)).flatten().tolist()
    if not failed:
        return out
    flat = _flat(out).clone()
    for i in failed:
        flat[i] = lu(i)
    return flat.reshape(out.shape)
