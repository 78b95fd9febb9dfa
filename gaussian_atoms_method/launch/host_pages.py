"""numpy's large arrays on the system's ordinary pages, in a launcher's own process only.

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
