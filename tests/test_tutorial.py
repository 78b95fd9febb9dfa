"""docs/tutorial.md runs as written: its Python blocks in one interpreter, then its bash blocks,
in a scratch directory with the data path pointed at ../shared/data (the only change)."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TUTORIAL = ROOT / "docs" / "tutorial.md"


def blocks(language: str) -> list[str]:
    return re.findall(rf"```{language}\n(.*?)```", TUTORIAL.read_text(), re.S)


def test_tutorial_runs(shared_data, tmp_path):
    data = shared_data / "asi208"
    if not data.is_dir():
        pytest.skip("no aSi-208 data")
    (tmp_path / ".venv").symlink_to(Path(sys.executable).parent.parent)  # the environment the tests run in
    python = "\n".join(blocks("python")).replace('DATA = "../shared/data/asi208"', f'DATA = "{data}"')
    run = subprocess.run([sys.executable, "-c", python], cwd=tmp_path, capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr[-3000:]
    found = re.search(r"found (\d+)/(\d+), false (\d+), RMSD ([\d.]+) pm", run.stdout)
    assert found, run.stdout[-2000:]
    # The tutorial promises what the benchmark measures at this dose (docs/results.md): every
    # atom, none false, and no worse than the authors' own pipeline (4.23 pm).
    assert (int(found[1]), int(found[2]), int(found[3])) == (208, 208, 0) and float(found[4]) < 4.23
    assert (tmp_path / "outputs" / "tutorial" / "atoms.png").is_file()
    for block in blocks("bash"):
        shell = subprocess.run(
            ["bash", "-euo", "pipefail", "-c", block.replace("../shared/data/asi208", str(data))],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            timeout=900,
        )
        assert shell.returncode == 0, shell.stderr[-3000:]
    run_dir = tmp_path / "outputs" / "tutorial-cli" / "asi208" / "gaussian-atoms" / "run"
    assert (
        (run_dir / "atoms.xyz").is_file()
        and (run_dir / "slices.png").is_file()
        and (tmp_path / "outputs" / "tutorial-cli" / "atoms.cif").is_file()
    )
