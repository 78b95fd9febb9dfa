"""Every study in scripts/studies/ is maintained: it starts and explains itself with --help from a fresh
clone, and the start-up profile runs on a tiny series."""

import subprocess
import sys
from pathlib import Path

import pytest

from gaussian_atoms_method.harness.input_cases import valid_series

SCRIPTS = sorted(
    p for p in (Path(__file__).resolve().parents[1] / "scripts" / "studies").iterdir() if p.suffix in (".py", ".sh")
)


def _run(script: Path, *args: str) -> subprocess.CompletedProcess:
    launcher = ["bash"] if script.suffix == ".sh" else [sys.executable]
    return subprocess.run(launcher + [str(script), *args], capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize("script", SCRIPTS, ids=[s.name for s in SCRIPTS])
def test_script_starts_with_help(script):
    run = _run(script, "--help")
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.lower().startswith("usage:")


def test_startup_profile_runs(tmp_path):
    run = _run(SCRIPTS[[s.name for s in SCRIPTS].index("startup_profile.py")], str(valid_series(tmp_path / "series")))
    assert run.returncode == 0, run.stderr[-2000:]
    phases = [line.split(":")[0] for line in run.stdout.splitlines() if line.endswith(" s")]
    assert "back-projection candidates on cpu" in phases and "model construction (includes the candidates)" in phases
