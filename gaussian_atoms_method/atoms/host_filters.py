"""scipy's 1-D filters along one axis of a volume, run over slabs in threads.

A filter along one axis treats every line along it on its own, so slabs cut across another
axis can be filtered apart and give scipy's own values, bit for bit.  scipy's ``ndimage``
releases the GIL while it filters, so the slabs run at once on every core the process may use
(``torch.get_num_threads()``).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import Callable

import numpy as np
import scipy

_POOL: dict[int, ThreadPoolExecutor] = {}


def _threads() -> int:
    import torch

    return max(1, torch.get_num_threads())


def along_axis(volume: np.ndarray, axis: int, one_d: Callable[[np.ndarray, int, np.ndarray], object]) -> np.ndarray:
    """``one_d(part, axis, out)`` (a scipy 1-D filter writing into ``out``) over ``volume``, in
    slabs across another axis, one thread each; returns the new array (``volume``'s dtype)."""
    out = np.empty_like(volume)
    across = 1 if axis == 0 else 0
    threads = _threads()
    # two slabs a thread: one slow to fault its fresh pages in does not hold the other thread idle
    k = min(2 * threads, volume.shape[across]) if volume.ndim > 1 and threads > 1 else 1
    if k <= 1:
        one_d(volume, axis, out)
        return out
    bounds = np.linspace(0, volume.shape[across], k + 1).astype(int)

    def run(i: int) -> None:
        cut = [slice(None)] * volume.ndim
        cut[across] = slice(bounds[i], bounds[i + 1])
        one_d(volume[tuple(cut)], axis, out[tuple(cut)])

    pool = _POOL.get(threads) or _POOL.setdefault(
        threads, ThreadPoolExecutor(threads, thread_name_prefix="host-filter")
    )
    for done in [pool.submit(run, i) for i in range(k)]:
        done.result()
    return out


def gaussian_pass(volume: np.ndarray, sigma: float, axis: int, order: int = 0) -> np.ndarray:
    """scipy's ``gaussian_filter1d(volume, sigma, axis, order)`` (``reflect``, ``truncate`` 4)."""
    return along_axis(
        volume,
        axis,
        lambda part, ax, out: scipy.ndimage.gaussian_filter1d(
            part, sigma, ax, order, output=out, mode="reflect", truncate=4.0
        ),
    )


def maximum_filter3(volume: np.ndarray) -> np.ndarray:
    """scipy's ``maximum_filter(volume, size=3, mode="nearest")``: its 1-D passes along each axis in turn."""
    for axis in range(volume.ndim):
        volume = along_axis(
            volume, axis, lambda part, ax, out: scipy.ndimage.maximum_filter1d(part, 3, ax, output=out, mode="nearest")
        )
    return volume
