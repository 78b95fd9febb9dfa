"""Packages nerfstudio imports at the top but a training run reads late or never, imported when
something first reads them.

* ``torchvision``: nerfstudio's pipeline module imports ``torchvision.utils`` for one call that
  saves evaluation images, and importing torchvision imports torch's compiler front end
  (dynamo, through ``torchvision.ops``).
* ``matplotlib``: nerfstudio's colour maps, imported through its COLMAP reader; this method's
  pictures (written after the atoms) import it when they are drawn.
* ``tensorly``: nerfstudio's bilateral grid (a splatfacto option this method does not build)
  imports it and sets its backend at import; the stand-in keeps the backend for the real
  package (0.45 s on the H100 machine, 0.7 s on the 2-core CPU).
* torch's compiler front end (``torch._dynamo``): ``torch.optim.Optimizer`` imports it the first
  time one of its methods runs (``torch._disable_dynamo``, which keeps the compiler out of those
  methods); :func:`defer_dynamo` leaves it unimported until something else imports it (0.7 s on
  the H100 machine, 2.8 s on the 2-core CPU, at the optimisers' set-up).
* torch's symbolic shapes (``torch.fx.experimental.symbolic_shapes``, and sympy with it):
  ``torch.broadcast_shapes`` imports them on its first call, which nerfstudio's cameras make
  each time one is built or indexed; :func:`defer_symbolic_shapes` broadcasts plain integer
  shapes without them (0.8 s of the start on the 2-core CPU).

Importing ``gaussian-atoms train`` took 8.9 s on the 2-core CPU, 3.0 s of it torchvision and
0.5 s matplotlib (``python -X importtime``); on the lent H200, 4.0-4.9 -> 2.6-3.6 s with
torchvision deferred.  :func:`defer_imports` puts stand-ins for those modules in ``sys.modules``;
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


def defer_dynamo() -> int:
    """Let ``torch.optim.Optimizer``'s methods run without importing ``torch._dynamo`` while no
    one else has imported it: each method ``torch._disable_dynamo`` wrapped calls its function
    as it is until then (nothing is being compiled without dynamo), and takes dynamo's disabled
    form, as torch would, once dynamo is imported.  Returns the methods changed (none where
    torch wraps them otherwise)."""
    import torch
    import torch._compile

    inner = torch._compile._disable_dynamo(lambda: None).__code__
    changed = 0
    for method in vars(torch.optim.Optimizer).values():
        fn = getattr(method, "__wrapped__", None)
        if (
            getattr(method, "__code__", None) is not inner
            or fn is None
            or getattr(fn, "__dynamo_disable", None) is not None
        ):
            continue
        fn.__dynamo_disable = _until_dynamo(fn, method)
        changed += 1
    return changed


def defer_symbolic_shapes() -> bool:
    """Let ``torch.broadcast_shapes`` broadcast shapes of plain ``int`` sizes without importing
    torch's symbolic shapes (and sympy): the same result, by the same rule; anything else
    (symbolic or nested sizes, a negative size, shapes that do not broadcast) goes to torch's own
    function, which raises its own errors.  Returns whether it was put in place."""
    import torch._refs

    original = torch._refs._broadcast_shapes
    if getattr(original, "_plain_ints", False):
        return False

    def broadcast(*shapes):
        common = _plain_broadcast(shapes)
        return original(*shapes) if common is None else common

    broadcast._plain_ints = True
    torch._refs._broadcast_shapes = broadcast
    return True


def _plain_broadcast(shapes) -> list[int] | None:
    """The broadcast of ``shapes`` (ints or sequences of ints, None entries skipped) as a list,
    where every size is a non-negative plain ``int`` and they broadcast; None otherwise (and
    for no shapes, which torch answers itself)."""
    sizes = []
    for shape in shapes:
        if shape is None:
            continue
        shape = (shape,) if type(shape) is int else shape  # torch.Size is a tuple
        if not isinstance(shape, (tuple, list)) or any(type(n) is not int or n < 0 for n in shape):
            return None
        sizes.append(shape)
    if not sizes:
        return None
    common = [1] * max(len(s) for s in sizes)
    for shape in sizes:
        for i in range(-1, -1 - len(shape), -1):
            if shape[i] == common[i] or shape[i] == 1:
                continue
            if common[i] != 1:
                return None  # incompatible: torch's own function says so
            common[i] = shape[i]
    return common


def _until_dynamo(fn, method):
    """``fn`` itself while ``torch._dynamo`` is not imported; from then on torch's own
    ``method`` (which makes and caches dynamo's disabled ``fn``)."""

    def call(*args, **kwargs):
        if "torch._dynamo" not in sys.modules:
            return fn(*args, **kwargs)
        del fn.__dynamo_disable
        return method(*args, **kwargs)

    return call
