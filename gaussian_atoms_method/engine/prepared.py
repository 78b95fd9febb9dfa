"""What a launcher prepared for a fit while its process started, handed to the fit as an
argument (:class:`Prepared`); the engine never asks a launcher for it.

``gaussian-atoms train`` and the plugin ``ns-train`` loads begin the run's start in a thread
while they import (:mod:`gaussian_atoms_method.launch`); a fit built with their
:class:`Prepared` takes that start where it was made from exactly its own inputs, and computes
its own otherwise.  A fit's result never depends on which.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable


def _none(*args, **kwargs) -> None:
    return None


@dataclass(frozen=True)
class Prepared:
    """A launcher's preparations, as three calls.

    Attributes
    ----------
    noise : callable
        ``noise(series)``: the noise measured for ``series``'s file, or None.
    start : callable
        ``start(series, projections, normalisation, extended_object, max_atom_sigma_A)``: the
        :class:`~gaussian_atoms_method.atoms.initialise.Start` made from exactly these inputs,
        or None; handed out once.
    quiet : callable
        ``quiet()``: returns once no thread of the launcher launches device work (a CUDA
        graph's capture breaks on another thread's launch).
    """

    noise: Callable[[object], object | None] = _none
    start: Callable[..., object | None] = _none
    quiet: Callable[[], None] = _none


NOTHING = Prepared()
"""Nothing prepared: the fit makes its own start (``ga.reconstruct`` and every fit the engine
builds itself)."""
