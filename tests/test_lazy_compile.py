"""splatfacto imported with its torch.compile deferred to the first call."""

import torch

from gaussian_atoms_method.nerfstudio_layer.lazy_compile import deferred_compile, import_splatfacto


def test_deferred_compile_compiles_on_first_call_and_gives_the_same_values():
    calls = []

    def scaled(x):
        calls.append(1)
        return 2.0 * x

    wrapped = deferred_compile(backend="eager")(scaled)
    assert calls == [] and wrapped.__name__ == "scaled"  # nothing compiled or run yet
    x = torch.arange(4.0)
    assert torch.equal(wrapped(x), 2.0 * x) and torch.equal(wrapped(x), 2.0 * x)


def test_import_splatfacto_leaves_nerfstudio_s_decorator_as_it_was():
    import nerfstudio.utils.misc as misc

    before = misc.torch_compile
    module = import_splatfacto()
    assert module.SplatfactoModel.__name__ == "SplatfactoModel" and misc.torch_compile is before
