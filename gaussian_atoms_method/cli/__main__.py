"""``python -m gaussian_atoms_method.cli``: the same as the ``gaussian-atoms`` command."""

from gaussian_atoms_method.cli import entrypoint

entrypoint()
