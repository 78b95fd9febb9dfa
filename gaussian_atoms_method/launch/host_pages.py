"""numpy's large arrays on the system's ordinary pages, and freed memory kept for the next
allocation (:func:`keep_freed_memory`), in a launcher's own process only.

numpy asks the kernel for transparent huge pages (``madvise(MADV_HUGEPAGE)``) for every array of
4 MB or more.  Where the kernel compacts memory to serve such a request (``defrag`` set to
``madvise``, a common default), a first touch of fresh memory may wait for that compaction, and
a run makes and frees arrays of 50-100 MB again and again (the residual search's
back-projection and its spectra, the evidence's tables).  On this 2-core CPU the first
back-projection of the Au noise-200 residuals took 2.2 s, 1.4 s of it system time; on ordinary
pages 1.2 s.  :func:`ordinary_pages` turns numpy's request off (as ``NUMPY_MADVISE_HUGEPAGE=0``
does) for the rest of the process; a user's own setting of that variable is kept, and
``ga.reconstruct`` leaves the caller's numpy as it is.
"""

from __future__ import annotations

import os

VARIABLE = "NUMPY_MADVISE_HUGEPAGE"
"""numpy's own switch: where the environment gives it, the launcher leaves numpy as it says."""


def ordinary_pages(environ=os.environ) -> bool:
    """Stop numpy asking for huge pages in this process unless ``environ`` sets
    :data:`VARIABLE`; returns whether it was stopped here."""
    if VARIABLE in environ:
        return False
    from numpy._core import multiarray

    multiarray._set_madvise_hugepage(False)
    return True


MALLOC_SETTINGS = ("MALLOC_MMAP_MAX_", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_")
"""glibc's own variables for what :func:`keep_freed_memory` sets (and ``GLIBC_TUNABLES``' ``glibc.malloc``
names): where the environment gives any of them, the launcher leaves malloc as it says."""

TRIM_THRESHOLD_BYTES = 1 << 30
"""The free memory at the heap's top that malloc keeps rather than handing back to the system: a
run's largest temporaries are 50-100 MB and its resident peak about 1.7 GB on the Au noise-200
particle, so a gigabyte kept free covers what the next step asks for again."""


def keep_freed_memory(environ=os.environ) -> bool:
    """Have glibc's malloc serve every allocation from its heap and keep what is freed (no
    ``mmap`` per large array, nothing trimmed below :data:`TRIM_THRESHOLD_BYTES`), in this process,
    unless ``environ`` sets malloc itself (:data:`MALLOC_SETTINGS`); returns whether it was set.

    glibc maps every allocation above 32 MB (and above a threshold that grows to that) afresh and
    unmaps it when freed, so each of a run's large temporaries, made again at every step, is paid
    for again in page faults: 3.1-3.3 million minor faults and 7.4-8.0 s of system time (11% of the
    user time) on the Au noise-200 run through ``gaussian-atoms train`` on this 2-core CPU, against
    1.0-1.2 million and 3.5 s (5%) with the heap kept (the same atoms.csv, the resident peak
    1.73-1.83 GB either way).  Without glibc (``mallopt`` not found) nothing is set."""
    import ctypes
    import ctypes.util

    if any(name in environ for name in MALLOC_SETTINGS) or "glibc.malloc" in environ.get("GLIBC_TUNABLES", ""):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    m_trim_threshold, m_mmap_max = -1, -4  # malloc.h
    return bool(mallopt(m_mmap_max, 0)) and bool(mallopt(m_trim_threshold, TRIM_THRESHOLD_BYTES))
