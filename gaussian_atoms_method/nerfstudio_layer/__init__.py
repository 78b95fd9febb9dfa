"""The thin nerfstudio layer: the method's config and trainer (:mod:`.config`), the splatfacto
subclass that is the engine's fit (:mod:`.model`, :class:`gaussian_atoms_method.engine.fit.AtomFit`),
the nerfstudio trainer's launcher for what only it serves (:mod:`.launch`) and the viewer's atom
cloud (:mod:`.viewer`).

The only modules of :mod:`gaussian_atoms_method` that import nerfstudio (with the
dataparser and dataset in :mod:`dataparsers`)."""
