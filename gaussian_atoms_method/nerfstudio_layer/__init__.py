"""The thin nerfstudio layer: the method's config and trainer (:mod:`.config`), the splatfacto
subclass that is the engine's fit (:mod:`.model`, :class:`gaussian_atoms_method.engine.fit.AtomFit`),
the nerfstudio trainer's launcher for what only it serves (:mod:`.launch`) and the viewer's atom
cloud (:mod:`.viewer`).

The only modules of :mod:`gaussian_atoms_method` that import nerfstudio (with the
dataparser and dataset in :mod:`dataparsers`)."""

from gaussian_atoms_method.launch.lean_torch import lean_torch
from gaussian_atoms_method.nerfstudio_layer.deferred_imports import defer_imports
from gaussian_atoms_method.nerfstudio_layer.lazy_compile import import_splatfacto

defer_imports()  # before nerfstudio imports them
lean_torch()
import_splatfacto()  # first, so that nerfstudio's own imports of it (trainer, viewer) find it made
