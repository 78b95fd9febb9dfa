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
        assert not isinstance(sys.modules["matplotlib"], DeferredModule) and plt.figure is sys.modules["matplotlib.pyplot"].figure
        print("ok")
        """
    )
    run = subprocess.run([sys.executable, "-W", "ignore", "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert run.returncode == 0 and run.stdout.strip().endswith("ok"), run.stderr[-2000:]


def test_an_imported_package_is_left_alone():
    import matplotlib

    from gaussian_atoms_method.nerfstudio_layer.deferred_imports import defer_imports

    assert "matplotlib" not in defer_imports() and sys.modules["matplotlib"] is matplotlib
