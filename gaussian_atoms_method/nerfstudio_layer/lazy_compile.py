"""Import nerfstudio's splatfacto without compiling at import time.

splatfacto decorates one of its functions with ``torch.compile`` when the module is imported,
which imports torch's compiler stack (inductor): 2.7 s of every launch of ``gaussian-atoms
train`` on the 2-core CPU (12.1 -> 9.4 s to import the plugin), for a function this method
never calls.  :func:`import_splatfacto` imports the module with that decorator deferred: the
function is compiled on its first call, as before, only later.  Where splatfacto is already
imported (``ns-train`` imports every method first) it changes nothing.
"""

from __future__ import annotations

import functools
import importlib
import sys


def deferred_compile(*args, **kwargs):
    """A decorator like ``torch.compile(*args, **kwargs)`` that compiles on the first call."""

    def decorate(fn):
        compiled = None

        @functools.wraps(fn)
        def call(*a, **k):
            nonlocal compiled
            if compiled is None:
                import torch

                compiled = torch.compile(fn, *args, **kwargs)
            return compiled(*a, **k)

        return call

    return decorate


def import_splatfacto():
    """``nerfstudio.models.splatfacto``, imported with its ``torch_compile`` decorator deferred
    (:func:`deferred_compile`) if this is its first import."""
    name = "nerfstudio.models.splatfacto"
    if name in sys.modules:
        return sys.modules[name]
    import nerfstudio.utils.misc as misc

    original = misc.torch_compile
    misc.torch_compile = deferred_compile
    try:
        return importlib.import_module(name)
    finally:
        misc.torch_compile = original
