"""Atom files: extended XYZ (readable by ASE), CSV and the AET 'type x y z' text."""

import ase.io
import numpy as np
import pytest

from gaussian_atoms_method.atoms.atom_set import AtomFileError, AtomSet, read_atoms, write_atoms


def _atoms():
    rng = np.random.default_rng(3)
    return AtomSet(
        rng.normal(size=(7, 3)) * 10,
        sigmas=rng.uniform(0.5, 0.8, 7),
        amplitudes=rng.uniform(1, 9, 7),
        species=["Au"] * 3 + ["Pt"] * 4,
        atom_class=[1, 1, 1, 2, 2, 2, 0],
    )


@pytest.mark.parametrize("suffix", [".xyz", ".extxyz", ".csv"])
def test_round_trip(tmp_path, suffix):
    a = _atoms()
    path = write_atoms(a, tmp_path / f"atoms{suffix}")
    b = read_atoms(path)
    # ASE's extended XYZ keeps 8 decimals: 1e-8 Å, far below any physical precision.
    np.testing.assert_allclose(b.positions, a.positions, rtol=0, atol=1e-7)
    np.testing.assert_allclose(b.sigmas, a.sigmas, rtol=1e-7)
    np.testing.assert_allclose(b.amplitudes, a.amplitudes, rtol=1e-7)
    assert list(b.species) == list(a.species)
    assert list(b.atom_class) == list(a.atom_class)


def test_xyz_is_plain_ase(tmp_path):
    a = _atoms()
    write_atoms(a, tmp_path / "atoms.xyz")
    atoms = ase.io.read(tmp_path / "atoms.xyz")
    np.testing.assert_allclose(atoms.get_positions(), a.positions, rtol=0, atol=1e-7)
    np.testing.assert_allclose(atoms.arrays["sigma_A"], a.sigmas, rtol=1e-7)


def test_type_xyz_text(tmp_path):
    p = tmp_path / "gt.txt"
    p.write_text("% 2\n% comment\n1  0.5 1.5 -2.0\n2  3 4 5\n")
    a = read_atoms(p)
    np.testing.assert_array_equal(a.positions, [[0.5, 1.5, -2.0], [3, 4, 5]])
    assert list(a.species) == ["1", "2"]


def test_peer_ground_truth_reads(shared_data):
    a = read_atoms(shared_data / "asi208" / "aSi_208atoms_GT.txt")
    assert len(a) == 208


def test_errors_name_the_file(tmp_path):
    with pytest.raises(AtomFileError, match="missing.xyz.*not found"):
        read_atoms(tmp_path / "missing.xyz")
    bad = tmp_path / "bad.txt"
    bad.write_text("1 2 3\n")
    with pytest.raises(AtomFileError, match="bad.txt:1"):
        read_atoms(bad)
    with pytest.raises(ValueError, match="unknown atom file type"):
        write_atoms(_atoms(), tmp_path / "atoms.pdbx")
    with pytest.raises(ValueError, match="sigmas has 2 entries for 3 atoms"):
        AtomSet(np.zeros((3, 3)), sigmas=[1.0, 2.0])


def test_write_is_atomic(tmp_path, monkeypatch):
    """A failing write leaves no file that looks complete."""
    import gaussian_atoms_method.atoms.atom_set as mod

    def boom(atoms, path):
        path.write_text("species,x_A\nAu,")
        raise RuntimeError("disk full")

    monkeypatch.setattr(mod, "_write_csv", boom)
    with pytest.raises(RuntimeError):
        write_atoms(_atoms(), tmp_path / "atoms.csv")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("optional", [True, False, "none"])
def test_xyz_and_csv_are_the_bytes_ase_and_csv_write(tmp_path, optional):
    """The one-pass writers give exactly what ASE's extended XYZ writer and csv.writer give
    (the formats every reader of these files has seen), with and without the optional columns,
    and for no atoms (a run's non_atoms.xyz)."""
    import csv

    a = _atoms()
    if optional == "none":
        a = a.subset(np.zeros(len(a), dtype=bool))
    elif optional:
        a.position_std_A = np.random.default_rng(4).uniform(0, 0.01, (len(a), 3))
        a.species = np.array(["Au", "Pt", "X", "Au", "O", "Pt", "Au"])
    else:
        a = AtomSet(a.positions)
    write_atoms(a, tmp_path / "ours.xyz")
    ase.io.write(tmp_path / "ase.xyz", a.to_ase(), format="extxyz")
    assert (tmp_path / "ours.xyz").read_bytes() == (tmp_path / "ase.xyz").read_bytes()
    write_atoms(a, tmp_path / "ours.csv")
    n = len(a)
    columns = {
        "species": a.species if a.species is not None else np.full(n, "X"),
        "x_A": a.positions[:, 0],
        "y_A": a.positions[:, 1],
        "z_A": a.positions[:, 2],
        "sigma_A": a.sigmas if a.sigmas is not None else np.full(n, np.nan),
        "amplitude": a.amplitudes if a.amplitudes is not None else np.full(n, np.nan),
    }
    if a.position_std_A is not None:
        columns.update({f"std_{axis}_A": a.position_std_A[:, k] for k, axis in enumerate("xyz")})
    if a.atom_class is not None:
        columns["class"] = a.atom_class
    with open(tmp_path / "csv.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(columns.keys())
        for i in range(n):
            writer.writerow(
                [columns["species"][i]]
                + [str(int(columns[k][i])) if k == "class" else repr(float(columns[k][i])) for k in list(columns)[1:]]
            )
    assert (tmp_path / "ours.csv").read_bytes() == (tmp_path / "csv.csv").read_bytes()


def test_a_file_read_twice_is_read_as_it_stands(tmp_path):
    """Reads of an unchanged file give equal atoms, each the caller's own; a rewritten file is read anew."""
    path = write_atoms(_atoms(), tmp_path / "atoms.xyz")
    first, second = read_atoms(path), read_atoms(path)
    np.testing.assert_array_equal(first.positions, second.positions)
    first.positions[0] = 99.0
    assert read_atoms(path).positions[0, 0] != 99.0
    write_atoms(AtomSet(np.ones((2, 3))), path)
    assert len(read_atoms(path)) == 2


def test_plain_extended_xyz_is_read_as_ase_reads_it(tmp_path):
    """The reader of plain one-frame extended XYZ (this package's files, simulations' truth)
    gives ASE's arrays to the bit, every column included; a file it does not take (a cell, two
    frames, an unknown species) is read by ASE as before, or refused by it."""
    import ase.data
    import ase.io

    from gaussian_atoms_method.atoms.atom_set import ELEMENTS, _read_plain_extxyz

    assert ELEMENTS == set(ase.data.chemical_symbols)  # the species list kept here is ASE's

    rng = np.random.default_rng(3)
    n = 300
    full = AtomSet(
        rng.normal(size=(n, 3)) * 12.3456789,
        rng.random(n) + 0.3,
        rng.random(n) * 5,
        np.array(["Au", "Si", "O"] * 100),
        position_std_A=rng.random((n, 3)) * 0.1,
        atom_class=rng.integers(0, 3, n),
    )
    for atoms in (full, AtomSet(full.positions, species=full.species)):
        path = write_atoms(atoms, tmp_path / "a.xyz")
        mine, theirs = _read_plain_extxyz(path), AtomSet.from_ase(ase.io.read(path))
        for name in ("positions", "sigmas", "amplitudes", "species", "position_std_A", "atom_class"):
            a, b = getattr(mine, name), getattr(theirs, name)
            assert (a is None and b is None) or (np.array_equal(a, b) and a.dtype == b.dtype), name
    text = (tmp_path / "a.xyz").read_text()
    others = {
        "cell.xyz": text.replace('pbc="F F F"', 'Lattice="20 0 0 0 20 0 0 0 20" pbc="T T T"'),
        "frames.xyz": text + text,
        "unknown.xyz": text.replace("\nAu ", "\nQq ", 1),
    }
    for name, content in others.items():
        (tmp_path / name).write_text(content)
        assert _read_plain_extxyz(tmp_path / name) is None
    written = read_atoms(tmp_path / "a.xyz").positions
    assert np.array_equal(read_atoms(tmp_path / "cell.xyz").positions, written)
    assert np.array_equal(read_atoms(tmp_path / "frames.xyz").positions, written)
    with pytest.raises(AtomFileError, match="unknown.xyz"):
        read_atoms(tmp_path / "unknown.xyz")
