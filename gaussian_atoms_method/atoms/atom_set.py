"""Atom sets in Å and their files.

An :class:`AtomSet` holds what the method solves for: positions in Å, a width (Gaussian
sigma, Å) and an amplitude per atom, and optionally a species.  It reads and writes extended
XYZ (through ASE, so every ASE reader works as input), CSV, and the ``type x y z`` text format
used by the AET community's ground-truth files.  Writes are atomic: a file either holds a
complete result or does not exist.
"""

from __future__ import annotations

import copy
import csv
import functools
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

EVIDENCE_FIELDS = {
    "atom_class": np.int64,
    "significance": np.float64,
    "proven": np.int64,
    "depth_halfwidth_A": np.float64,
    "depth_open": np.int64,
    "depth_rise": np.float64,
    "element_confidence": np.float64,
    "width_std_A": np.float64,
    "log_mass_std": np.float64,
    "width_open": np.int64,
    "mass_open": np.int64,
    "trusted": np.int64,
}
"""The per-atom (N,) columns after the position's precision: the class and each atom's evidence
(:mod:`gaussian_atoms_method.atoms.evidence`), by name and type."""

CSV_INTEGER_COLUMNS = frozenset({"class", "proven", "depth_open", "width_open", "mass_open", "trusted"})
"""The CSV columns written as whole numbers."""


class AtomFileError(ValueError):
    """A file of atoms could not be read: names the file and the problem."""


@dataclass
class AtomSet:
    """Atoms with positions in Å.

    Attributes
    ----------
    positions : (N, 3) float array, Å
    sigmas : (N,) float array, Å, or None
        Gaussian width of each atom's potential (as reconstructed, including blur).
    amplitudes : (N,) float array or None
        3D peak of each Gaussian, in units of the input projections per Å.
    species : (N,) array of str, or None
    position_std_A : (N, 3) float array, Å, or None
        Estimated standard deviation of each position along x, y, z
        (:mod:`gaussian_atoms_method.atoms.uncertainty`).
    atom_class : (N,) int array, or None
        Each Gaussian's class (:mod:`gaussian_atoms_method.atoms.classification`): 1..k by
        increasing mass for atoms, 0 for a non-atom.
    significance : (N,) float array, or None
        What the views lose if the atom is taken out with its neighbours re-fitted, in standard
        deviations of the noise (:mod:`gaussian_atoms_method.atoms.evidence`).
    proven : (N,) int array, or None
        1 where the significance proves the atom, 0 where the data leave it open.
    depth_halfwidth_A : (N,) float array, or None
        Half-width of the 95% interval along the direction the views fix least (the beam).
    depth_open : (N,) int array, or None
        1 where that interval is wider than half the hard core, or another place along the beam
        fits within it.
    depth_rise : (N,) float array, or None
        How much worse the best other place along the beam fits (the atom moved by half a hard
        core or more, its neighbours re-fitted), in the atom's stated variance along the beam:
        under 1.96^2 that place lies within its 95% interval; NaN where none was tried.
    element_confidence : (N,) float array, or None
        The probability of the element written, by the atom's mass among the elements' mass
        populations (:func:`~gaussian_atoms_method.atoms.species.classify_species`); NaN where the
        masses could not tell the elements apart.
    width_std_A : (N,) float array, or None
        The precision of the atom's width, found as its position's is.
    log_mass_std : (N,) float array, or None
        The precision of the logarithm of the atom's mass (its relative precision), its neighbours
        re-fitted (:attr:`~gaussian_atoms_method.atoms.evidence.AtomEvidence.log_mass_std`).
    width_open : (N,) int array, or None
        1 where the atom is wider than one atom of its element by more than its width's precision
        allows (:func:`~gaussian_atoms_method.atoms.calibration.wider_than_one_atom`): its image
        may hold two atoms the fit did not part.
    mass_open : (N,) int array, or None
        1 where the atom's mass lies beyond its element's population by more than the proof level
        allows (:func:`~gaussian_atoms_method.atoms.trust.mass_unlike_one_atom`): it may hold two
        atoms, or part of one.
    trusted : (N,) int array, or None
        1 where nothing the run read leaves the atom open: proven, closed in depth, one atom
        wide and, with several elements, its element sure
        (:func:`~gaussian_atoms_method.atoms.trust.open_atoms`); 0 where something does.
    """

    positions: np.ndarray
    sigmas: np.ndarray | None = None
    amplitudes: np.ndarray | None = None
    species: np.ndarray | None = None
    info: dict = field(default_factory=dict)
    position_std_A: np.ndarray | None = None
    atom_class: np.ndarray | None = None
    significance: np.ndarray | None = None
    proven: np.ndarray | None = None
    depth_halfwidth_A: np.ndarray | None = None
    depth_open: np.ndarray | None = None
    depth_rise: np.ndarray | None = None
    element_confidence: np.ndarray | None = None
    width_std_A: np.ndarray | None = None
    log_mass_std: np.ndarray | None = None
    width_open: np.ndarray | None = None
    mass_open: np.ndarray | None = None
    trusted: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.positions = np.asarray(self.positions, dtype=np.float64).reshape(-1, 3)
        n = len(self.positions)
        for name in ("sigmas", "amplitudes"):
            value = getattr(self, name)
            if value is not None:
                value = np.asarray(value, dtype=np.float64).reshape(-1)
                if len(value) != n:
                    raise ValueError(f"{name} has {len(value)} entries for {n} atoms")
                setattr(self, name, value)
        if self.position_std_A is not None:
            self.position_std_A = np.asarray(self.position_std_A, dtype=np.float64).reshape(-1, 3)
            if len(self.position_std_A) != n:
                raise ValueError(f"position_std_A has {len(self.position_std_A)} rows for {n} atoms")
        for name, dtype in EVIDENCE_FIELDS.items():
            value = getattr(self, name)
            if value is not None:
                value = np.asarray(value, dtype=dtype).reshape(-1)
                if len(value) != n:
                    raise ValueError(f"{name} has {len(value)} entries for {n} atoms")
                setattr(self, name, value)
        if self.species is not None:
            self.species = np.asarray(self.species, dtype=str).reshape(-1)
            if len(self.species) != n:
                raise ValueError(f"species has {len(self.species)} entries for {n} atoms")

    def __len__(self) -> int:
        return len(self.positions)

    @property
    def masses(self) -> np.ndarray | None:
        """Integrated potential of each Gaussian, ``amplitude (2 pi sigma^2)^(3/2)``."""
        if self.sigmas is None or self.amplitudes is None:
            return None
        return self.amplitudes * (2.0 * np.pi * self.sigmas**2) ** 1.5

    def subset(self, mask) -> "AtomSet":
        """The atoms where the (N,) bool ``mask`` (or index array) selects, every attribute alike."""

        def pick(v):
            return None if v is None else v[mask]

        return AtomSet(
            self.positions[mask],
            pick(self.sigmas),
            pick(self.amplitudes),
            pick(self.species),
            dict(self.info),
            pick(self.position_std_A),
            **{name: pick(getattr(self, name)) for name in EVIDENCE_FIELDS},
        )

    def shifted(self, offset_A) -> "AtomSet":
        """A copy with every position moved by ``offset_A`` (3,)."""
        return AtomSet(
            self.positions + np.asarray(offset_A, dtype=np.float64),
            self.sigmas,
            self.amplitudes,
            self.species,
            dict(self.info),
            self.position_std_A,
            **{name: getattr(self, name) for name in EVIDENCE_FIELDS},
        )

    # ------------------------------------------------------------------ ASE
    def to_ase(self):
        """An :class:`ase.Atoms`; sigma and amplitude become per-atom arrays."""
        import ase

        symbols = list(self.species) if self.species is not None else ["X"] * len(self)
        atoms = ase.Atoms(symbols=symbols, positions=self.positions, pbc=False)
        if self.sigmas is not None:
            atoms.new_array("sigma_A", self.sigmas)
        if self.amplitudes is not None:
            atoms.new_array("amplitude", self.amplitudes)
        if self.position_std_A is not None:
            atoms.new_array("position_std_A", self.position_std_A)
        for name in EVIDENCE_FIELDS:
            if getattr(self, name) is not None:
                atoms.new_array(name, getattr(self, name))
        return atoms

    @classmethod
    def from_ase(cls, atoms) -> "AtomSet":
        arrays = atoms.arrays
        species = np.array(atoms.get_chemical_symbols())
        return cls(
            positions=atoms.get_positions(),
            sigmas=arrays.get("sigma_A"),
            amplitudes=arrays.get("amplitude"),
            species=species,
            position_std_A=arrays.get("position_std_A"),
            **{name: arrays.get(name) for name in EVIDENCE_FIELDS},
        )


def current_umask() -> int:
    """The process's umask (read by setting it and setting it back)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _atomic_write(path: Path, write) -> None:
    """Write through a temporary file in the same folder, then rename: never half a file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=path.suffix)
    os.close(fd)
    try:
        write(Path(tmp))
        os.chmod(tmp, 0o666 & ~current_umask())  # mkstemp makes it 0600; the file follows the umask as open() would
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_atoms(atoms: AtomSet, path: str | Path) -> Path:
    """Write atoms to ``.xyz``/``.extxyz`` (extended XYZ) or ``.csv``, chosen by suffix, or
    ``.cif`` (species and positions; a cubic cell 10 Å wider than the atoms, positions shifted
    by half the cell on each axis, since a cell cannot hold negative coordinates)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in (".xyz", ".extxyz"):
        _atomic_write(path, lambda p: _write_extxyz(atoms, p))
    elif suffix == ".cif":
        import ase.io

        crystal = atoms.to_ase()
        side = 2 * float(np.abs(atoms.positions).max(initial=0.0)) + 10.0
        crystal.set_cell([side, side, side])
        crystal.translate([side / 2] * 3)
        _atomic_write(path, lambda p: ase.io.write(p, crystal, format="cif"))
    elif suffix == ".csv":
        _atomic_write(path, lambda p: _write_csv(atoms, p))
    else:
        raise ValueError(f"{path}: unknown atom file type {suffix!r}; expected .xyz, .extxyz, .csv or .cif")
    return path


EXTXYZ_COLUMNS = {
    "pos": ("positions", "R", 3),
    "sigma_A": ("sigmas", "R", 1),
    "amplitude": ("amplitudes", "R", 1),
    "position_std_A": ("position_std_A", "R", 3),
    "atom_class": ("atom_class", "I", 1),
    "significance": ("significance", "R", 1),
    "proven": ("proven", "I", 1),
    "depth_halfwidth_A": ("depth_halfwidth_A", "R", 1),
    "depth_open": ("depth_open", "I", 1),
    "depth_rise": ("depth_rise", "R", 1),
    "element_confidence": ("element_confidence", "R", 1),
    "width_std_A": ("width_std_A", "R", 1),
    "log_mass_std": ("log_mass_std", "R", 1),
    "width_open": ("width_open", "I", 1),
    "mass_open": ("mass_open", "I", 1),
    "trusted": ("trusted", "I", 1),
}
"""The per-atom columns of this package's extended XYZ after the species, in the order
:meth:`AtomSet.to_ase` adds them: name -> (:class:`AtomSet` field, ASE's type letter, width)."""


def _extxyz_columns(atoms: AtomSet) -> list[tuple[str, np.ndarray, str]]:
    """(name, (N, k) values, ASE's type letter) of each of :data:`EXTXYZ_COLUMNS` the atoms hold."""
    n, columns = len(atoms), []
    for name, (field_name, kind, _) in EXTXYZ_COLUMNS.items():
        values = getattr(atoms, field_name)
        if values is not None:
            columns.append((name, values.reshape(n, -1), kind))
    return columns


def _write_extxyz(atoms: AtomSet, path: Path) -> None:
    """Extended XYZ, the bytes ASE's writer gives :meth:`AtomSet.to_ase` (tests/test_atoms_io.py):
    its formats (``%-2s``, ``%16.8f``, ``%8d``) applied a row at a time in one pass, where ASE
    formats column by column through its own machinery, several times slower at many atoms."""
    if len(atoms) == 0:  # ASE's own header for no atoms (its column types read from empty arrays)
        import ase.io

        return ase.io.write(path, atoms.to_ase(), format="extxyz")
    n, columns = len(atoms), _extxyz_columns(atoms)
    species = (atoms.species if atoms.species is not None else np.full(n, "X")).tolist()
    properties = ":".join(["species:S:1"] + [f"{name}:{kind}:{values.shape[1]}" for name, values, kind in columns])
    row = (
        "%-2s" + "".join((" %16.8f" if kind == "R" else " %8d") * values.shape[1] for _, values, kind in columns) + "\n"
    )
    numbers = np.hstack([values.astype(np.float64) for _, values, _ in columns]).tolist()
    with open(path, "w") as f:
        f.write(f'{n}\nProperties={properties} pbc="F F F"\n')
        f.writelines(row % (s, *r) for s, r in zip(species, numbers))


def _write_csv(atoms: AtomSet, path: Path) -> None:
    n = len(atoms)
    columns = {
        "species": atoms.species if atoms.species is not None else np.full(n, "X"),
        "x_A": atoms.positions[:, 0],
        "y_A": atoms.positions[:, 1],
        "z_A": atoms.positions[:, 2],
        "sigma_A": atoms.sigmas if atoms.sigmas is not None else np.full(n, np.nan),
        "amplitude": atoms.amplitudes if atoms.amplitudes is not None else np.full(n, np.nan),
    }
    if atoms.position_std_A is not None:
        for k, axis in enumerate("xyz"):
            columns[f"std_{axis}_A"] = atoms.position_std_A[:, k]
    for name in EVIDENCE_FIELDS:
        if getattr(atoms, name) is not None:
            columns["class" if name == "atom_class" else name] = getattr(atoms, name)
    # Each value as csv.writer writes repr(float) and str(int), a row at a time (csv.writer's
    # own loop took 1.15 s for 54,000 atoms on the 2-core CPU); species with a comma or a quote
    # go through csv's quoting.
    species = [
        f'"{x.replace(chr(34), chr(34) * 2)}"' if ("," in x or '"' in x) else x
        for x in np.asarray(columns["species"]).astype(str).tolist()
    ]
    names = list(columns)[1:]
    integer = [k in CSV_INTEGER_COLUMNS for k in names]
    rows = np.stack([np.asarray(columns[k], dtype=np.float64) for k in names], axis=1).tolist()
    with open(path, "w", newline="") as f:
        f.write(",".join(columns.keys()) + "\r\n")
        f.writelines(
            ",".join([s, *(str(int(v)) if whole else repr(v) for v, whole in zip(r, integer))]) + "\r\n"
            for s, r in zip(species, rows)
        )


def read_atoms(path: str | Path) -> AtomSet:
    """Read atoms from extended XYZ / any ASE format, our CSV, or ``type x y z`` text.

    Text files whose comment lines start with ``%`` or ``#`` and whose rows are
    ``type x y z`` (the AET ground-truth format) are read as such.
    """
    path = Path(path)
    if not path.is_file():
        raise AtomFileError(f"{path}: atom file not found")
    stat = path.stat()
    # the caller's own arrays
    return copy.deepcopy(_read_unchanged(path.resolve(), stat.st_ino, stat.st_mtime_ns, stat.st_size))


@functools.lru_cache(maxsize=4)
def _read_unchanged(path: Path, inode: int, mtime_ns: int, size: int) -> AtomSet:
    """:func:`read_atoms` of a file as it stands (its inode, modification time and size: an
    atomic write makes a new inode): a run reads
    its truth file when it checks the input and again when it scores."""
    suffix = path.suffix.lower()
    try:
        if suffix == ".csv":
            return _read_csv(path)
        if suffix == ".txt":
            return _read_type_xyz_text(path)
        plain = _read_plain_extxyz(path) if suffix in (".xyz", ".extxyz") else None
        if plain is not None:
            return plain
        import ase.io

        return AtomSet.from_ase(ase.io.read(path))
    except AtomFileError:
        raise
    except Exception as exc:  # ASE and numpy raise many types; name the file
        raise AtomFileError(f"{path}: could not read atoms ({type(exc).__name__}: {exc})") from exc


ELEMENTS = frozenset(
    "X H He Li Be B C N O F Ne Na Mg Al Si P S Cl Ar K Ca Sc Ti V Cr Mn Fe Co Ni Cu Zn Ga Ge As Se Br Kr "
    "Rb Sr Y Zr Nb Mo Tc Ru Rh Pd Ag Cd In Sn Sb Te I Xe Cs Ba La Ce Pr Nd Pm Sm Eu Gd Tb Dy Ho Er Tm Yb "
    "Lu Hf Ta W Re Os Ir Pt Au Hg Tl Pb Bi Po At Rn Fr Ra Ac Th Pa U Np Pu Am Cm Bk Cf Es Fm Md No Lr Rf "
    "Db Sg Bh Hs Mt Ds Rg Cn Nh Fl Mc Lv Ts Og".split()
)
"""The species ASE's extended XYZ reader accepts (``ase.data.chemical_symbols``)."""


def _read_plain_extxyz(path: Path) -> AtomSet | None:
    """A one-frame extended XYZ file of the plain form this package and simulations write (a
    comment line of only ``Properties=species:S:1:pos:R:3[...]`` of :data:`EXTXYZ_COLUMNS` and
    ``pbc="F F F"``, known species), read without ASE: what ``ase.io.read`` gives for it
    (tests/test_atoms_io.py), without ASE's import on the launch's input check.  None for
    anything else (ASE reads it)."""
    with open(path) as f:
        text = f.read()
    head, _, rest = text.partition("\n")
    comment, _, body = rest.partition("\n")
    fields = comment.split()
    if (
        not head.strip().isdigit()
        or len(fields) != 4
        or fields[1:] != ['pbc="F', "F", 'F"']
        or not fields[0].startswith("Properties=species:S:1:")
    ):
        return None
    spec = fields[0][len("Properties=species:S:1:") :].split(":")
    if len(spec) % 3 or spec[:3] != ["pos", "R", "3"]:
        return None
    columns = [
        (spec[i], spec[i + 1], int(spec[i + 2])) if spec[i + 2].isdigit() else (None, None, 0)
        for i in range(0, len(spec), 3)
    ]
    if any(EXTXYZ_COLUMNS.get(name, (None,))[1:] != (kind, width) for name, kind, width in columns) or len(
        {c[0] for c in columns}
    ) != len(columns):
        return None
    n, width = int(head), 1 + sum(w for _, _, w in columns)
    tokens = body.split()
    if len(tokens) != n * width:
        return None  # more frames, or a malformed one: ASE's reader decides
    table = np.array(tokens, dtype=object).reshape(n, width)
    species = table[:, 0].astype(str)
    if not set(species.tolist()) <= ELEMENTS:
        return None
    arrays, at = {"species": species}, 1
    try:
        for name, kind, w in columns:
            block = table[:, at : at + w].astype(np.int64 if kind == "I" else np.float64)
            arrays[EXTXYZ_COLUMNS[name][0]] = block if w > 1 else block[:, 0]
            at += w
    except ValueError:
        return None
    return AtomSet(**arrays)


def _read_csv(path: Path) -> AtomSet:
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        return AtomSet(np.zeros((0, 3)))
    missing = {"x_A", "y_A", "z_A"} - set(rows[0])
    if missing:
        raise AtomFileError(f"{path}: CSV lacks column(s) {sorted(missing)}; expected x_A, y_A, z_A")
    pos = np.array([[float(r["x_A"]), float(r["y_A"]), float(r["z_A"])] for r in rows])
    sig = np.array([float(r.get("sigma_A", "nan")) for r in rows])
    amp = np.array([float(r.get("amplitude", "nan")) for r in rows])
    species = np.array([r.get("species", "X") for r in rows])
    std = np.array([[float(r[f"std_{a}_A"]) for a in "xyz"] for r in rows]) if "std_x_A" in rows[0] else None
    evidence = {
        name: np.array([float(r["class" if name == "atom_class" else name]) for r in rows])
        for name in EVIDENCE_FIELDS
        if ("class" if name == "atom_class" else name) in rows[0]
    }
    return AtomSet(
        pos,
        None if np.isnan(sig).all() else sig,
        None if np.isnan(amp).all() else amp,
        species,
        position_std_A=std,
        **evidence,
    )


def _read_type_xyz_text(path: Path) -> AtomSet:
    rows = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        line = line.strip()
        if not line or line[0] in "%#":
            continue
        parts = line.split()
        if len(parts) != 4:
            raise AtomFileError(f"{path}:{lineno}: expected 'type x y z', got {line!r}")
        rows.append(parts)
    species = np.array([r[0] for r in rows])
    pos = np.array([[float(v) for v in r[1:]] for r in rows]).reshape(-1, 3)
    return AtomSet(pos, species=species)
