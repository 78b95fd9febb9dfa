"""gaussian-atoms: atoms straight from an atomic-electron-tomography tilt series.

The physics core (geometry, projector, atoms and their files, merge, metrics, simulation)
imports no nerfstudio; ``config`` and ``model`` are the thin nerfstudio layer.
"""

__version__ = "0.1.0"
