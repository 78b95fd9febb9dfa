"""Packages nerfstudio imports at the top but a training run reads late or never, imported when
something first reads them.

* ``torchvision``: nerfstudio's pipeline module imports ``torchvision.utils`` for one call that
  saves evaluation images, and importing torchvision imports torch's compiler front end
  (dynamo, through ``torchvision.ops``).
* ``matplotlib``: nerfstudio's colour maps, imported through its COLMAP reader; this method's
  pictures (written after the atoms) import it when they are drawn.
* ``tensorly``: nerfstudio's bilateral grid (a splatfacto option this method does not build)
  imports it and sets its backend at import; the stand-in keeps the backend for the real
  package.

torch's own late imports (its compiler front end, its symbolic shapes) are the engine's
(:mod:`gaussian_atoms_method.launch.lean_torch`).

Importing ``gaussian-atoms train`` took 8.9 s on the 2-core CPU, 3.0 s of it torchvision
(``python -X importtime``).  :func:`defer_imports` puts stand-ins for those modules in ``sys.modules``;
the first attribute read of one (or an import of another of its submodules) imports the real
package, and the stand-ins forward to it from then on.  A package already imported
(``ns-train`` imports every method first) or not installed is left alone.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
import types

DEFERRED = {"torchvision": ("utils",), "matplotlib": (), "tensorly": ()}
"""Each deferred package and the submodules nerfstudio imports by name (``import
torchvision.utils as vutils`` reads the attribute of a stand-in parent)."""


class DeferredModule(types.ModuleType):
    """A module not imported yet: the first attribute it lacks imports the real one."""

    def __getattr__(self, attr: str):
        if attr.startswith("__") and attr not in ("__path__", "__all__", "__version__"):
            raise AttributeError(attr)  # probes of every module (inspect reads __file__) import nothing
        return getattr(load_deferred(self.__name__), attr)


class DeferredTensorly(DeferredModule):
    """tensorly's stand-in: ``set_backend`` (what nerfstudio calls at import) is kept and applied
    to the real package when it is imported."""

    def set_backend(self, backend, local_threadsafe: bool = False) -> None:
        self.__dict__["_backend"] = (backend, local_threadsafe)


def load_deferred(name: str) -> types.ModuleType:
    """Import the real module ``name`` in place of its package's stand-ins."""
    package = name.partition(".")[0]
    pending = []
    for stand_in in [package, *(f"{package}.{sub}" for sub in DEFERRED.get(package, ()))]:
        if isinstance(sys.modules.get(stand_in), DeferredModule):
            pending.append(sys.modules.pop(stand_in).__dict__.get("_backend"))
    module = importlib.import_module(name)
    for backend in filter(None, pending):
        importlib.import_module(package).set_backend(*backend)
    return module


def defer_imports() -> list[str]:
    """Put the stand-ins in ``sys.modules`` for each package of :data:`DEFERRED` not imported
    yet and installed; returns the packages deferred."""
    deferred = []
    for package, submodules in DEFERRED.items():
        if package in sys.modules or importlib.util.find_spec(package) is None:
            continue
        parent = sys.modules[package] = (DeferredTensorly if package == "tensorly" else DeferredModule)(package)
        for sub in submodules:
            child = sys.modules[f"{package}.{sub}"] = DeferredModule(f"{package}.{sub}")
            setattr(parent, sub, child)
        deferred.append(package)
    return deferred
