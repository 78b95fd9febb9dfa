"""Test particles for the accuracy harness, built with ASE / numpy, positions in Å.

* ``au``: the paper's 6,679-atom fcc gold particle (bundled, see ``data/README.md``);
* ``fept``: an FePt sphere of several L1_0-ordered grains with random orientations (grain
  boundaries), about 8,000 atoms;
* ``apd``: amorphous Pd, about 16,000 atoms: a dense random packing relaxed until no two atoms
  are closer than 2.5 Å (near the 2.75 Å Pd-Pd bond), not a lattice;
* ``apd-close``: amorphous Pd with the close pairs of a measured amorphous structure: the packing
  relaxed to 2.4 Å, each atom then displaced by a normal 0.12 Å per axis, so that about 2% of the
  atoms have a neighbour under 2.0 Å and 30% under 2.2 Å (:func:`close_packing`);
* ``hea``: an amorphous Ni-Pd-Pt high-entropy alloy on the same kind of packing (equal parts);
* ``carbon``: a light, dense, disordered carbon: a diamond network compressed to 1.49 Å bonds
  with 0.025 Å random displacements (nearest neighbours 1.37-1.53 Å, as short as amorphous
  carbon's), a 7,000-atom sphere;
* ``asi``: a large amorphous silicon particle, 20,000 atoms: the same packing at a-Si's number
  density (0.049 atoms/Å^3: 2.28 g/cm^3) with no two atoms closer than 2.2 Å (the Si-Si bond is
  2.35 Å); a 91 Å sphere, for the size the benchmarks must reach;
* anything ASE can read.

``scale`` shrinks a particle linearly (atom count ~ scale^3) for quick tests: ``au`` is cut to
a sphere of ``scale`` times its radius about its centre, the others are built smaller.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from gaussian_atoms_method.atoms.atom_set import AtomSet, read_atoms

DATA_DIR = Path(__file__).parent / "data"
PARTICLES = ("au", "fept", "apd", "apd-close", "hea", "carbon", "asi", "film")


def make_particle(name_or_path: str, scale: float = 1.0, seed: int = 0) -> AtomSet:
    """A named test particle, or atoms read from a structure file; centred on its centroid.

    ``scale`` is the linear size factor: the generated particles (all but ``au`` and files) grow
    or shrink, a particle read from a file is cut to a smaller sphere (``scale`` at most 1)."""
    if not scale > 0:
        raise ValueError(f"scale must be positive, got {scale}")
    if scale > 1.0 and (name_or_path == "au" or name_or_path not in PARTICLES):
        raise ValueError(f"scale must be at most 1 for {name_or_path!r} (cut from a structure file), got {scale}")
    rng = np.random.default_rng(seed)
    if name_or_path == "au":
        atoms = _cut_sphere(read_atoms(DATA_DIR / "Au_NP.xyz"), scale)
    elif name_or_path == "fept":
        atoms = polycrystal_l10(
            radius_A=29.7 * scale, n_grains=max(1, round(6 * scale**3)) if scale < 1 else 6, rng=rng
        )
    elif name_or_path == "apd":
        atoms = amorphous_packing(n_atoms=int(round(16000 * scale**3)), species=("Pd",), min_distance_A=2.5, rng=rng)
    elif name_or_path == "apd-close":
        atoms = close_packing(n_atoms=int(round(16000 * scale**3)), species=("Pd",), rng=rng)
    elif name_or_path == "hea":
        atoms = amorphous_packing(
            n_atoms=int(round(16000 * scale**3)), species=("Ni", "Pd", "Pt"), min_distance_A=2.4, rng=rng
        )
    elif name_or_path == "asi":
        atoms = amorphous_packing(
            n_atoms=int(round(20000 * scale**3)),
            species=("Si",),
            min_distance_A=2.2,
            rng=rng,
            number_density_per_A3=0.049,
        )
    elif name_or_path == "film":
        # Amorphous Pd, 20 Å thick, 110 Å across the tilt axis and 50 Å along it: wider than a 40 Å
        # field of view by what rays at 70 degrees cross (20 Å x tan 70 = 55 Å), and going on
        # past the detector's edges along the axis as a film does.
        atoms = amorphous_packing(
            n_atoms=0,
            species=("Pd",),
            min_distance_A=2.5,
            rng=rng,
            box_A=(110.0 * scale, 50.0 * scale, 20.0),
            periodic_xy=True,
        )
    elif name_or_path == "carbon":
        atoms = disordered_carbon(n_atoms=int(round(7000 * scale**3)), rng=rng)
    else:
        path = Path(name_or_path)
        if not path.is_file():
            raise ValueError(f"particle {name_or_path!r}: expected one of {PARTICLES} or a structure file that exists")
        atoms = _cut_sphere(read_atoms(path), scale)
    return atoms.shifted(-atoms.positions.mean(axis=0))


def _cut_sphere(atoms: AtomSet, scale: float) -> AtomSet:
    if scale >= 1.0:
        return atoms
    centre = atoms.positions.mean(axis=0)
    r = np.linalg.norm(atoms.positions - centre, axis=1)
    keep = r <= scale * r.max()
    return AtomSet(atoms.positions[keep], species=None if atoms.species is None else atoms.species[keep])


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def polycrystal_l10(
    radius_A: float,
    n_grains: int,
    rng: np.random.Generator,
    a_A: float = 3.85,
    c_A: float = 3.71,
    min_distance_A: float = 2.2,
) -> AtomSet:
    """A sphere of L1_0 FePt grains (Voronoi cells of random seeds, random orientations).

    Atoms from neighbouring grains closer than ``min_distance_A`` are thinned so that grain
    boundaries stay physical.
    """
    # L1_0: Fe at (0,0,0),(1/2,1/2,0); Pt at (1/2,0,1/2),(0,1/2,1/2) in an a x a x c cell.
    basis = np.array([[0, 0, 0], [0.5, 0.5, 0], [0.5, 0, 0.5], [0, 0.5, 0.5]]) * [a_A, a_A, c_A]
    kinds = np.array(["Fe", "Fe", "Pt", "Pt"])
    n = int(np.ceil(2 * radius_A * np.sqrt(3) / min(a_A, c_A))) + 2
    idx = np.arange(-n, n + 1)
    cells = np.stack(np.meshgrid(idx, idx, idx, indexing="ij"), -1).reshape(-1, 3) * [a_A, a_A, c_A]
    lattice = (cells[:, None, :] + basis[None]).reshape(-1, 3)
    lattice_kinds = np.tile(kinds, len(cells))
    seeds = rng.uniform(-radius_A, radius_A, size=(n_grains, 3)) * 0.7
    pos, spe = [], []
    for g in range(n_grains):
        p = lattice @ _random_rotation(rng).T + rng.uniform(0, a_A, 3)
        inside = np.linalg.norm(p, axis=1) <= radius_A
        owner = (
            np.argmin(np.linalg.norm(p[:, None, :] - seeds[None], axis=-1), axis=1)
            if n_grains > 1
            else np.zeros(len(p), int)
        )
        keep = inside & (owner == g)
        pos.append(p[keep])
        spe.append(lattice_kinds[keep])
    pos, spe = np.concatenate(pos), np.concatenate(spe)
    pos, spe = _thin(pos, spe, min_distance_A)
    return AtomSet(pos, species=spe)


def _thin(pos: np.ndarray, species: np.ndarray, min_distance_A: float) -> tuple[np.ndarray, np.ndarray]:
    """Drop one atom of every pair closer than ``min_distance_A`` until none is left."""
    keep = np.ones(len(pos), bool)
    pairs = cKDTree(pos).query_pairs(min_distance_A, output_type="ndarray")
    for i, j in pairs:  # grain-boundary pairs only: a few hundred at most
        if keep[i] and keep[j]:
            keep[j] = False
    return pos[keep], species[keep]


def amorphous_packing(
    n_atoms: int,
    species: tuple[str, ...],
    min_distance_A: float,
    rng: np.random.Generator,
    number_density_per_A3: float = 0.066,
    box_A: tuple[float, float, float] | None = None,
    periodic_xy: bool = False,
) -> AtomSet:
    """A dense random packing in a sphere of ``n_atoms``, or in a box of sides ``box_A`` (x, y, z)
    at the number density (a film): random points pushed apart to a minimum distance.  With
    ``periodic_xy`` the box is periodic in x and y (a piece of a wider film: no atoms piled on
    its side faces).

    Starts from uniform random points at the metallic-glass number density and repeatedly
    moves every pair closer than ``min_distance_A`` apart along their axis (vectorised, k-d
    tree) until no pair is closer than 0.98 of it.  Species are assigned at random in equal parts.
    """
    if box_A is not None:
        half = 0.5 * np.asarray(box_A, dtype=np.float64)
        n_atoms = int(round(number_density_per_A3 * np.prod(2.0 * half)))
    if n_atoms < 1:
        raise ValueError("n_atoms must be at least 1")
    radius = (3 * n_atoms / (4 * np.pi * number_density_per_A3)) ** (1 / 3)
    if box_A is not None:
        pos = rng.uniform(-half, half, (n_atoms, 3))
    else:
        u = rng.normal(size=(n_atoms, 3))
        pos = u / np.linalg.norm(u, axis=1, keepdims=True) * radius * rng.uniform(0, 1, (n_atoms, 1)) ** (1 / 3)
    period = np.array([2.0 * half[0], 2.0 * half[1], 0.0]) if (box_A is not None and periodic_xy) else None
    for _ in range(500):
        if period is not None:  # cKDTree's periodic box: coordinates in [0, L), z unbounded (a large box)
            pairs = cKDTree(
                pos + [half[0], half[1], half[2] + 1.0], boxsize=[period[0], period[1], 4.0 * half[2] + 8.0]
            ).query_pairs(min_distance_A, output_type="ndarray")
        else:
            pairs = cKDTree(pos).query_pairs(min_distance_A, output_type="ndarray")
        if len(pairs) == 0:
            break
        d = pos[pairs[:, 1]] - pos[pairs[:, 0]]
        if period is not None:
            d[:, :2] -= period[:2] * np.round(d[:, :2] / period[:2])
        dist = np.linalg.norm(d, axis=1, keepdims=True).clip(1e-6)
        push = 0.5 * (min_distance_A * 1.02 - dist) * d / dist
        move = np.zeros_like(pos)
        np.add.at(move, pairs[:, 0], -push)
        np.add.at(move, pairs[:, 1], push)
        pos += move
        # Keep the shape: pull escapees back to the surface.
        if period is not None:
            pos[:, :2] = (pos[:, :2] + half[:2]) % period[:2] - half[:2]
            pos[:, 2] = np.clip(pos[:, 2], -half[2], half[2])
        elif box_A is not None:
            pos = np.clip(pos, -half, half)
        else:
            r = np.linalg.norm(pos, axis=1, keepdims=True)
            pos = np.where(r > radius, pos * radius / r, pos)
    spe = np.array(species)[rng.permutation(n_atoms) % len(species)]
    return AtomSet(pos, species=spe)


CLOSE_MIN_DISTANCE_A = 2.4
""":func:`close_packing`'s relaxed minimum distance, Å."""
CLOSE_DISPLACEMENT_A = 0.12
""":func:`close_packing`'s displacement, Å per axis.  With :data:`CLOSE_MIN_DISTANCE_A` the pair
distribution of measured amorphous Pd particles (atomic electron tomography: about 2% of atoms
with a neighbour under 2.0 Å, 28% under 2.2 Å); on 16,000 atoms 1.9% and 30% (2.45 Å and
0.14 Å: 2.8% and 28%; 2.5 Å and 0.16 Å: 3.7% and 28%)."""


def close_packing(
    n_atoms: int,
    species: tuple[str, ...],
    rng: np.random.Generator,
    min_distance_A: float = CLOSE_MIN_DISTANCE_A,
    displacement_A: float = CLOSE_DISPLACEMENT_A,
) -> AtomSet:
    """:func:`amorphous_packing` to ``min_distance_A``, each atom then displaced by a normal
    ``displacement_A`` per axis: a glass whose nearest neighbours spread below the relaxed
    distance as a measured one's do, so that some pairs are closer than a fit resolves easily."""
    atoms = amorphous_packing(n_atoms, species, min_distance_A, rng)
    moved = atoms.positions + rng.normal(0.0, displacement_A, atoms.positions.shape)
    return AtomSet(moved, species=atoms.species)


def disordered_carbon(
    n_atoms: int, rng: np.random.Generator, bond_A: float = 1.49, displacement_A: float = 0.025
) -> AtomSet:
    """A sphere of ``n_atoms`` carbon atoms on a diamond network scaled to ``bond_A`` bonds
    (diamond's own is 1.545 Å), each displaced by a normal ``displacement_A`` per axis and the
    whole turned at random: nearest neighbours at 1.4-1.55 Å, 4-fold coordinated, no long-range
    order visible from any tilt."""
    a = bond_A * 4.0 / np.sqrt(3.0)  # diamond: bond = a sqrt(3) / 4
    n = int(np.ceil((n_atoms / 8.0 * 6.0 / np.pi) ** (1.0 / 3.0))) + 2
    cells = np.stack(np.meshgrid(*[np.arange(-n, n + 1)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    basis = np.array(
        [
            [0, 0, 0],
            [0, 0.5, 0.5],
            [0.5, 0, 0.5],
            [0.5, 0.5, 0],
            [0.25, 0.25, 0.25],
            [0.25, 0.75, 0.75],
            [0.75, 0.25, 0.75],
            [0.75, 0.75, 0.25],
        ]
    )
    pos = ((cells[:, None, :] + basis[None]) * a).reshape(-1, 3)
    pos = pos[np.argsort(np.linalg.norm(pos, axis=1), kind="stable")[:n_atoms]]
    pos = pos @ _random_rotation(rng).T + rng.normal(0.0, displacement_A, pos.shape)
    return AtomSet(pos, species=np.array(["C"] * len(pos)))
