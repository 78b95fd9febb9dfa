"""torch run without the parts of it a fit never uses, which torch imports on first use.

* torch's compiler front end (``torch._dynamo``): ``torch.optim.Optimizer`` imports it the first
  time one of its methods runs (``torch._disable_dynamo``, which keeps the compiler out of those
  methods), and Adam's step at its first call (to mark graph breaks for compiled code);
  :func:`defer_dynamo` and :func:`defer_dynamo_in_adam` leave it unimported until something
  else imports it (2.8 s on the 2-core CPU, at the optimisers' set-up and first step).
* torch's symbolic shapes (``torch.fx.experimental.symbolic_shapes``, and sympy with it):
  ``torch.broadcast_shapes`` imports them on its first call, which nerfstudio's cameras make
  each time one is built or indexed; :func:`defer_symbolic_shapes` broadcasts plain integer
  shapes without them.

All are put in place by :func:`lean_torch` in a launcher's own process (``gaussian-atoms
train`` before its fit, ``ns-train gaussian-atoms`` as the plugin loads), never by
``ga.reconstruct`` in a user's, and change nothing once something else has imported the module
they defer.
"""

from __future__ import annotations

import inspect
import sys


def lean_torch() -> None:
    """:func:`defer_dynamo`, :func:`defer_dynamo_in_adam` and :func:`defer_symbolic_shapes`
    (each once)."""
    defer_dynamo()
    defer_dynamo_in_adam()
    defer_symbolic_shapes()


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


def defer_dynamo_in_adam() -> bool:
    """Let ``torch.optim.Adam``'s step run without importing ``torch._dynamo`` while no one else
    has imported it: in eager mode the stock step's graph-break marks do nothing, and the step is
    the update itself with gradients off, as the stock one runs it (the same floats:
    ``tests/test_lean_torch.py``); once dynamo is imported, the stock step.  Torch's profiling
    hooks wrap it as they wrap the stock one.  Returns whether it was put in place."""
    import torch

    stock = torch.optim.Adam.step
    if getattr(stock, "_until_dynamo", False) or getattr(inspect.unwrap(stock), "_until_dynamo", False):
        return False
    update = inspect.unwrap(stock)  # the update, without the stock step's wrappers
    with_graph_breaks = _wrapper_layer(stock, "_use_grad")  # the stock step without its profiling hooks
    if with_graph_breaks is None:
        return False  # a torch whose step is wrapped otherwise: left as it is

    def step(self, closure=None):
        if "torch._dynamo" in sys.modules:  # something compiles, or may
            return with_graph_breaks(self, closure)
        with torch.set_grad_enabled(self.defaults["differentiable"]):
            return update(self, closure)

    step._until_dynamo = True
    torch.optim.Adam.step = step
    return True


def _wrapper_layer(fn, name: str):
    """The layer of the decorated ``fn`` whose code is named ``name`` (None if none is)."""
    while fn is not None and getattr(getattr(fn, "__code__", None), "co_name", None) != name:
        fn = getattr(fn, "__wrapped__", None)
    return fn


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
