"""torchvision and matplotlib imported only when something reads them (nerfstudio_layer/deferred_imports.py)."""

import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_the_plugin_leaves_torchvision_unimported_until_it_is_read():
    """In a fresh interpreter: importing the plugin and nerfstudio's pipeline imports neither
    torchvision (nor torch's dynamo) nor matplotlib; nerfstudio's ``vutils`` then reads the real
    function, another submodule imports as usual, and importing a submodule first (pyplot)
    brings the real package."""
    code = textwrap.dedent(
        """
        import sys
        import gaussian_atoms_method.nerfstudio_layer
        import nerfstudio.pipelines.base_pipeline as pipeline
        from gaussian_atoms_method.nerfstudio_layer.deferred_imports import DeferredModule
        assert isinstance(sys.modules["torchvision"], DeferredModule) and isinstance(pipeline.vutils, DeferredModule)
        assert "torch._dynamo" not in sys.modules and "torchvision.models" not in sys.modules
        import inspect
        inspect.getmodule(pipeline)  # reads every module's __file__: imports nothing
        assert isinstance(sys.modules["torchvision"], DeferredModule)
        save_image = pipeline.vutils.save_image
        import torchvision.utils
        assert save_image is torchvision.utils.save_image and not isinstance(sys.modules["torchvision"], DeferredModule)
        import torchvision.transforms.functional
        assert isinstance(sys.modules["matplotlib"], DeferredModule)
        import matplotlib.pyplot as plt  # a submodule imported first: the real package comes with it
        assert not isinstance(sys.modules["matplotlib"], DeferredModule)
        assert plt.figure is sys.modules["matplotlib.pyplot"].figure
        print("ok")
        """
    )
    run = subprocess.run(
        [sys.executable, "-W", "ignore", "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300
    )
    assert run.returncode == 0 and run.stdout.strip().endswith("ok"), run.stderr[-2000:]


def test_an_imported_package_is_left_alone():
    import matplotlib

    from gaussian_atoms_method.nerfstudio_layer.deferred_imports import defer_imports

    assert "matplotlib" not in defer_imports() and sys.modules["matplotlib"] is matplotlib


def test_tensorly_and_dynamo_wait_until_something_uses_them():
    """In a fresh interpreter: splatfacto's import (the bilateral grid sets tensorly's backend)
    and an optimiser's set-up, steps and state leave tensorly and torch's dynamo unimported;
    tensorly's first use brings the real package with the backend nerfstudio set, and once
    dynamo is imported the optimiser's methods take its disabled form, as torch gives them."""
    code = textwrap.dedent(
        """
        import sys
        import gaussian_atoms_method.nerfstudio_layer
        import nerfstudio.models.splatfacto
        import torch
        from gaussian_atoms_method.engine.optimisers import Adam
        assert "tensorly" in sys.modules and "torch._dynamo" not in sys.modules
        p, q = torch.nn.Parameter(torch.ones(3)), torch.nn.Parameter(torch.ones(3))
        opt, stock = Adam([p], lr=0.1), torch.optim.Adam([q], lr=0.1)
        for _ in range(3):
            (p * torch.arange(3.0)).sum().backward(); opt.step(); opt.zero_grad()
        opt.load_state_dict(opt.state_dict())
        assert "torch._dynamo" not in sys.modules and float(p[1]) < 1.0
        for _ in range(3):  # the stock step (it imports dynamo): the same update, to the bit
            (q * torch.arange(3.0)).sum().backward(); stock.step(); stock.zero_grad()
        assert torch.equal(p, q) and "torch._dynamo" in sys.modules
        (p * torch.arange(3.0)).sum().backward(); opt.step()  # now through the stock step's graph breaks
        from nerfstudio.model_components import lib_bilagrid
        assert lib_bilagrid.tl.get_backend() == "pytorch"
        opt.add_param_group({"params": [torch.nn.Parameter(torch.ones(2))]})
        fn = torch.optim.Optimizer.add_param_group.__wrapped__
        assert fn.__dynamo_disable.__module__.startswith("torch._dynamo") or "_dynamo" in repr(fn.__dynamo_disable)
        print("ok")
        """
    )
    run = subprocess.run(
        [sys.executable, "-W", "ignore", "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300
    )
    assert run.returncode == 0 and run.stdout.strip().endswith("ok"), run.stderr[-2000:]


def test_broadcast_shapes_of_plain_ints_match_torchs_own_without_sympy():
    """In a fresh interpreter: the plugin's import, nerfstudio's cameras built and indexed leave
    torch's symbolic shapes (and sympy) unimported; the plain-int broadcast agrees with torch's
    own function on every pair and triple of small shapes, and shapes that do not broadcast get
    torch's own error."""
    code = textwrap.dedent(
        """
        import itertools, sys
        import torch
        import gaussian_atoms_method.nerfstudio_layer
        from gaussian_atoms_method.launch.lean_torch import _plain_broadcast
        from nerfstudio.cameras.cameras import Cameras, CameraType
        poses = torch.eye(4)[:3].expand(5, 3, 4)
        ortho = CameraType.ORTHOPHOTO
        cams = Cameras(camera_to_worlds=poses, fx=1.0, fy=1.0, cx=4.0, cy=4.0, width=8, height=8, camera_type=ortho)
        cams[2:4], cams[torch.tensor([1])]
        assert "sympy" not in sys.modules and "torch.fx.experimental.symbolic_shapes" not in sys.modules
        shapes = [(), (0,), (1,), (3,), (1, 1), (2, 1), (1, 3), (2, 3), (0, 3), (4, 1, 3)]
        checked = 0
        for combo in itertools.chain(itertools.product(shapes, repeat=2), itertools.product(shapes, repeat=3)):
            mine = _plain_broadcast(combo)
            try:
                expected = list(torch.broadcast_tensors(*(torch.empty(s) for s in combo))[0].shape)
            except RuntimeError:
                expected = None
            assert mine == expected, (combo, mine, expected)
            checked += mine is not None
        assert checked > 500
        try:
            torch.broadcast_shapes((2,), (3,))
            raise SystemExit("no error")
        except RuntimeError as e:
            assert "broadcast" in str(e)
        print("ok")
        """
    )
    run = subprocess.run(
        [sys.executable, "-W", "ignore", "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300
    )
    assert run.returncode == 0 and run.stdout.strip().endswith("ok"), run.stderr[-2000:]
