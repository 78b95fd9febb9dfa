"""The thin nerfstudio layer: the method's config (:mod:`.config`), the splatfacto subclass
(:mod:`.model`) with its per-view rendering (:mod:`gaussian_atoms_method.engine.rendering`), convergence check
(:mod:`gaussian_atoms_method.engine.convergence`) and result writing (:mod:`gaussian_atoms_method.engine.results`), the
training launchers
(:mod:`.launch`: ``gaussian-atoms train``; :mod:`.launch`: a minimal loop for tests), and the
viewer's atom cloud (:mod:`.viewer`).

The only modules of :mod:`gaussian_atoms_method` that import nerfstudio (with the
dataparser and dataset in :mod:`dataparsers`)."""

from gaussian_atoms_method.engine.lean_torch import lean_torch
from gaussian_atoms_method.nerfstudio_layer.deferred_imports import defer_imports
from gaussian_atoms_method.nerfstudio_layer.lazy_compile import import_splatfacto

defer_imports()  # before nerfstudio imports them
lean_torch()
import_splatfacto()  # first, so that nerfstudio's own imports of it (trainer, viewer) find it made
