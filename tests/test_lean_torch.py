"""torch without its compiler front end and symbolic shapes in a launcher's own process (launch/lean_torch.py), and
nothing of it in another ``ns-train``."""

import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_adam_steps_without_dynamo_and_the_same_floats_as_torchs_own():
    """In a fresh interpreter with :func:`lean_torch`: an Adam's set-up, steps and state leave
    torch's dynamo unimported and update to the bit as torch's own step (which imports it);
    once dynamo is imported the optimiser's methods take its disabled form, as torch gives them,
    and torch's profiling hooks still run once a step."""
    code = textwrap.dedent(
        """
        import sys
        import torch
        stock_step = torch.optim.Adam.step
        from gaussian_atoms_method.launch.lean_torch import lean_torch
        lean_torch()
        assert torch.optim.Adam.step is not stock_step
        p, q = torch.nn.Parameter(torch.ones(3)), torch.nn.Parameter(torch.ones(3))
        opt, other = torch.optim.Adam([p], lr=0.1), torch.optim.Adam([q], lr=0.1)
        calls = []
        opt.register_step_pre_hook(lambda *a: calls.append(1))
        for _ in range(3):
            (p * torch.arange(3.0)).sum().backward(); opt.step(); opt.zero_grad()
        opt.load_state_dict(opt.state_dict())
        assert "torch._dynamo" not in sys.modules and float(p[1]) < 1.0 and calls == [1, 1, 1]
        for _ in range(3):  # torch's own step (it imports dynamo): the same update, to the bit
            (q * torch.arange(3.0)).sum().backward(); stock_step(other); other.zero_grad()
        assert torch.equal(p, q) and "torch._dynamo" in sys.modules
        (p * torch.arange(3.0)).sum().backward(); opt.step()  # now through the stock step's graph breaks
        assert calls == [1, 1, 1, 1]
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


def test_the_plugin_leaves_another_ns_train_as_it_found_it():
    """In a fresh interpreter that is not ``ns-train gaussian-atoms``: importing the plugin's
    method config, as every ``ns-train`` does, leaves torch's Adam step and broadcast, tyro's
    ``cli``, nerfstudio's ``torch_compile`` and the switch interval as they were, and puts no
    stand-in into ``sys.modules``; the launch's preparations are this method's own
    (``launch/ns_train.py``)."""
    code = textwrap.dedent(
        """
        import sys, types
        import torch, torch._refs, tyro
        import nerfstudio.utils.misc as misc
        state = lambda: (torch.optim.Adam.step, torch._refs._broadcast_shapes, tyro.cli, misc.torch_compile,
                         sys.getswitchinterval())
        before, modules = state(), set(sys.modules)
        import gaussian_atoms_method.nerfstudio_layer.config
        assert state() == before
        odd = [k for k in set(sys.modules) - modules if not isinstance(sys.modules[k], types.ModuleType)
               or type(sys.modules[k]).__module__.startswith("gaussian_atoms")]
        assert not odd, odd
        print("ok")
        """
    )
    run = subprocess.run(
        [sys.executable, "-W", "ignore", "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300
    )
    assert run.returncode == 0 and run.stdout.strip().endswith("ok"), run.stderr[-2000:]


def test_broadcast_shapes_of_plain_ints_match_torchs_own_without_sympy():
    """In a fresh interpreter: with :func:`lean_torch`, nerfstudio's cameras built and indexed
    leave torch's symbolic shapes (and sympy) unimported; the plain-int broadcast agrees with torch's
    own function on every pair and triple of small shapes, and shapes that do not broadcast get
    torch's own error."""
    code = textwrap.dedent(
        """
        import itertools, sys
        import torch
        from gaussian_atoms_method.launch.lean_torch import _plain_broadcast, lean_torch
        lean_torch()
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
