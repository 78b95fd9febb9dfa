"""The one file ``pyproject.toml`` cannot place: ``gaussian_atoms_quiet.pth`` at the root of
site-packages, where Python runs it as it starts.  It hides torch's and nerfstudio's own
deprecation notes in an ``ns-train gaussian-atoms`` process only (nerfstudio raises them while
importing its cameras, before it loads any plugin:
:mod:`gaussian_atoms_method.launch.quiet_warnings`); any other process it leaves as it was."""

from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

HOOK = "gaussian_atoms_quiet.pth"
SOURCE = str(Path("gaussian_atoms_method") / "launch" / HOOK)


class BuildPyWithHook(build_py):
    """setuptools' ``build_py``, the hook copied beside the packages."""

    def run(self) -> None:
        super().run()
        self.copy_file(SOURCE, str(Path(self.build_lib) / HOOK))
        if getattr(self, "editable_mode", False):  # an editable wheel holds what lies in its install_lib
            self.copy_file(SOURCE, str(Path(self.get_finalized_command("install").install_lib) / HOOK))

    def get_outputs(self, include_bytecode: bool = True) -> list[str]:
        return [*super().get_outputs(include_bytecode), str(Path(self.build_lib) / HOOK)]


setup(cmdclass={"build_py": BuildPyWithHook})
