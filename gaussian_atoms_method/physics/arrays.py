"""Array helpers the hot paths share."""

from __future__ import annotations

import numpy as np


def unique_keys(keys) -> np.ndarray:
    """The distinct values of the integer array ``keys``, ascending: ``np.unique(keys)`` by a sort.

    numpy 2.4's ``np.unique`` finds distinct values through a hash table first; on 5 million
    int64 keys of a depth profile's table it took 5.3 s on this project's 2-core CPU, a sort
    and a comparison of neighbours 0.10 s.

    Examples
    --------
    >>> unique_keys(np.array([3, 1, 3, 2, 1]))
    array([1, 2, 3])
    """
    flat = np.sort(np.asarray(keys).ravel())
    if flat.size == 0:
        return flat
    return flat[np.r_[True, flat[1:] != flat[:-1]]]
