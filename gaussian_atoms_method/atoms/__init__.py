"""Atoms as a set of isotropic Gaussians, and what is done to such a set.

* :mod:`.atom_set`: :class:`AtomSet` (positions, widths and amplitudes in Å) and its files;
* :mod:`.candidates`: candidate atoms from a smoothed back-projection, as named steps;
* :mod:`.initialise`: where the Gaussians start (the candidates or random) and their masses;
* :mod:`.point_response`: one atom's smoothed back-projection, and peaks taken CLEAN-style;
* :mod:`.residual_sites`: where the residuals hold mass no Gaussian explains;
* :mod:`.merge`: the cluster merge (minimum-distance prior) as pure array functions;
* :mod:`.resolution`: whether the data tell two nearby Gaussians from one (the merge's chi-square);
* :mod:`.matching`: matching predicted to true atoms and the paper's scores;
* :mod:`.maxima`: local maxima of a volume and their suppression within a distance, on the host and on a device;
* :mod:`.peaks`: sub-voxel peaks and the height a noise field's peaks stay below;
* :mod:`.species`: species from integrated masses;
* :mod:`.uncertainty`: each atom's Cramér-Rao position precision;
* :mod:`.slices`: a figure of central slices of the potential with the atoms.

Depends on :mod:`gaussian_atoms_method.physics` only; no nerfstudio.
"""

from .atom_set import AtomFileError, AtomSet, read_atoms, write_atoms

__all__ = ["AtomFileError", "AtomSet", "read_atoms", "write_atoms"]
