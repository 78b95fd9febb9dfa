"""gaussian-atoms: atoms straight from an atomic-electron-tomography tilt series.

    import gaussian_atoms_method as ga
    atoms = ga.reconstruct(projections, angles_deg, pixel_size_A)   # :mod:`.api`
    series = ga.read_tilt_series("data/au")

Subpackages, lowest layer first (each imports only from the layers before it;
``docs/architecture.md`` draws the path from a tilt series to ``atoms.xyz``):

* :mod:`.physics`: geometry, projector, reconstruction, units (torch and numpy);
* :mod:`.atoms`: AtomSet and its files, the start, merge, matching, species, precision;
* :mod:`.density`: density control (duplicate, prune, merge) as a strategy;
* ``dataparsers.tilt_series_format`` / ``dataparsers.readers`` (top level): the input formats;
* :mod:`.nerfstudio_layer`: config, model, launchers, viewer (with ``dataparsers``'
  dataparser and dataset, the only nerfstudio importers);
* :mod:`.film`: a film in overlapping sub-areas on Ray, joined (``reconstruct_film``, ``tile_series``);
* :mod:`.api`: :func:`reconstruct` and :func:`read_tilt_series`, the Python entrance;
* :mod:`.harness`: simulation, baselines, metrics, benchmarks, sweeps, stress cases;
* :mod:`.cli`: the ``gaussian-atoms`` verbs.

Importing this package imports nothing else: the API's names load on first use.
"""

__version__ = "0.1.0"

__all__ = ["AtomSet", "InputError", "TiltSeries", "read_tilt_series", "reconstruct", "reconstruct_film", "tile_series"]
_FILM = {"reconstruct_film": "gaussian_atoms_method.film.film", "tile_series": "gaussian_atoms_method.film.subareas"}


def __getattr__(name: str):
    if name in _FILM:
        import importlib

        return getattr(importlib.import_module(_FILM[name]), name)
    if name in __all__:
        from gaussian_atoms_method import api

        return getattr(api, name)
    raise AttributeError(f"module 'gaussian_atoms_method' has no attribute {name!r}")
