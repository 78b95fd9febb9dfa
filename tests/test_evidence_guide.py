"""docs/evidence.md shows today's output: the lines its example says the demo prints are the ones
the demo's fit prints now (the same data as ``make demo``, the same fit through
``gaussian-atoms train``)."""

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


def _example_lines() -> list[str]:
    """The lines of docs/evidence.md's first console block (the demo's evidence lines)."""
    text = (ROOT / "docs" / "evidence.md").read_text()
    block = re.search(r"The run says what its residual is beside the atoms:\n\n```\n(.*?)```", text, re.S)
    assert block, "docs/evidence.md lost its example of the evidence lines"
    return [line for line in block[1].splitlines() if line.strip()]


def test_the_evidence_guides_example_is_what_the_demo_prints_today(tmp_path):
    """Each example line, its elisions ``(...)`` aside, is in the demo fit's console (the
    console's wrapping undone), in order: a change that moves a number the guide quotes fails here
    until the guide says it."""
    data = tmp_path / "demo"
    simulate = [str(BIN / "gaussian-atoms"), "simulate", "--output", str(data), "--particle", "sphere"]
    simulate += ["--element", "Au", "--radius-A", "11", "--potential", "gaussian", "--tilts", "limited"]
    made = subprocess.run(simulate + ["--noise-std", "20"], capture_output=True, text=True, timeout=600)
    assert made.returncode == 0, made.stderr
    train = [str(BIN / "gaussian-atoms"), "train", "--machine.device-type", "cpu", "--vis", "tensorboard"]
    train += ["--output-dir", str(tmp_path / "runs"), "tilt-series", "--data", str(data)]
    run = subprocess.run(train, capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr[-2000:]
    console = " ".join((run.stdout + run.stderr).split())
    at = 0
    for line in _example_lines():
        for part in (" ".join(p.split()) for p in line.split("(...)")):
            found = console.find(part, at)
            assert found >= 0, f"docs/evidence.md says {part!r}; the demo printed:\n{run.stdout[-3000:]}"
            at = found + len(part)
