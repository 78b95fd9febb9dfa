"""The README's commands run as written: every command in its bash blocks parses with the
options it gives (the verbs are built, not run: the end-to-end tests run the main ones at tiny
sizes); ``make`` targets named exist; the simulate example makes the sphere it says.  And the
package as a wheel carries its data (the Au particle) into a fresh environment."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest
import tyro

ROOT = Path(__file__).resolve().parents[1]


def readme_commands() -> list[list[str]]:
    """Each command of README.md's ```bash blocks as argv (continuations joined, comments dropped)."""
    text = (ROOT / "README.md").read_text()
    commands = []
    for block in re.findall(r"```bash\n(.*?)```", text, re.S):
        joined = re.sub(r"\\\n\s*", " ", block)
        for line in joined.splitlines():
            line = line.split("#", 1)[0].strip()
            if line:
                commands.append(shlex.split(line))
    return commands


def _parse(argv: list[str]) -> object:
    """Build (not run) what the command would run; raises SystemExit on an option that does not parse."""
    program = Path(argv[0]).name
    if program == "make":
        makefile = (ROOT / "Makefile").read_text()
        return all(re.search(rf"^{re.escape(t)}:", makefile, re.M) for t in argv[1:]) or None
    if program == "ns-train":
        from gaussian_atoms_method.nerfstudio_layer.launch import build_config

        assert argv[1] == "gaussian-atoms"
        return build_config(argv[2:])
    if program == "gaussian-atoms":
        from gaussian_atoms_method.cli import parse

        return parse(argv[1:])
    if program == "ns-viewer":
        assert argv[1:2] == ["--load-config"] and len(argv) == 3
        return argv[2]
    raise AssertionError(f"README command with an unknown program: {shlex.join(argv)}")


@pytest.mark.parametrize("argv", readme_commands(), ids=lambda a: shlex.join(a)[:70])
def test_readme_command_parses(argv):
    result = _parse(argv)
    assert result is not None, f"Makefile lacks a target of: {shlex.join(argv)}"


def test_readme_simulate_example_makes_the_sphere_it_says(tmp_path):
    """The first example once left out --particle sphere and silently simulated the 6,679-atom
    Au particle; options that would be ignored are now refused."""
    from gaussian_atoms_method.cli import Simulate

    example = next(a for a in readme_commands() if a[1:2] == ["simulate"] and "--radius-A" in a)
    command = tyro.cli(
        Simulate, args=[*example[2:], "--output", str(tmp_path / "s"), "--tilts", "-60:60:60", "--no-save-volume"]
    )
    command.main()
    n_atoms = sum(1 for _ in open(tmp_path / "s" / "atoms_true.xyz")) - 2
    assert 300 < n_atoms < 400  # an 11 Å Au sphere: 321 atoms (make demo's)
    with pytest.raises(ValueError, match="--element and --radius-A apply to --particle sphere"):
        tyro.cli(Simulate, args=["--element", "Au", "--radius-A", "11"]).main()


def test_stated_python_requirement_is_the_real_one():
    """README and pyproject say 3.11; the pinned numpy needs it."""
    assert "Python 3.11 or newer" in (ROOT / "README.md").read_text()
    assert 'requires-python = ">=3.11"' in (ROOT / "pyproject.toml").read_text()
    numpy_pin = re.search(r"^numpy==(\d+)\.(\d+)", (ROOT / "constraints.txt").read_text(), re.M)
    assert (int(numpy_pin[1]), int(numpy_pin[2])) >= (2, 3)  # numpy >= 2.3 requires Python >= 3.11


def test_wheel_carries_the_au_particle(tmp_path):
    """Build a wheel, install it into a fresh venv (dependencies taken from this environment
    through a .pth, not this checkout), and simulate the paper's Au particle from it."""
    dist = tmp_path / "dist"
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(dist), str(ROOT)],
        check=True,
        capture_output=True,
    )
    wheel = next(dist.glob("gaussian_atoms-*.whl"))
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    python = venv / "bin" / "python"
    site = Path(
        subprocess.run(
            [str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    )
    subprocess.run(
        [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", str(site), str(wheel)],
        check=True,
        capture_output=True,
    )
    (site / "dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    code = (
        "import gaussian_atoms_method, sys; from gaussian_atoms_method.harness.particles import make_particle; "
        "print(gaussian_atoms_method.__file__); print(len(make_particle('au', 0.3, 0)))"
    )
    run = subprocess.run([str(python), "-c", code], capture_output=True, text=True, cwd=tmp_path)
    assert run.returncode == 0, run.stderr[-2000:]
    module_file, n_atoms = run.stdout.split()[-2:]
    assert module_file.startswith(str(site)) and int(n_atoms) > 50
