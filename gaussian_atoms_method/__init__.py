"""gaussian-atoms: atoms straight from an atomic-electron-tomography tilt series.

Subpackages, lowest layer first (each imports only from the layers before it;
``docs/architecture.md`` draws the path from a tilt series to ``atoms.xyz``):

* :mod:`.physics`: geometry, projector, reconstruction, units (torch and numpy);
* :mod:`.atoms`: AtomSet and its files, the start, merge, matching, species, precision;
* :mod:`.density`: density control (duplicate, prune, merge) as a strategy;
* ``dataparsers.tilt_series_format`` / ``dataparsers.readers`` (top level): the input formats;
* :mod:`.nerfstudio_layer`: config, model, launchers, viewer (with ``dataparsers``'
  dataparser and dataset, the only nerfstudio importers);
* :mod:`.harness`: simulation, baselines, metrics, benchmarks, sweeps, stress cases;
* :mod:`.cli`: the ``gaussian-atoms`` verbs.

Importing this package imports nothing else.
"""

__version__ = "0.1.0"
