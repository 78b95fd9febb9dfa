"""nerfstudio's viewer in headless Chromium shows the atoms (``gaussian-atoms screenshot``).

Needs Debian's chromium and chromium-driver and the selenium package; skipped without them
(CI has no browser).
"""

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

from gaussian_atoms_method.harness import viewer_screenshot

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent

pytestmark = pytest.mark.skipif(
    viewer_screenshot.chromium_paths() is None or importlib.util.find_spec("selenium") is None,
    reason="headless Chromium (chromium, chromium-driver) or selenium not installed",
)


def test_viewer_screenshot_shows_atoms(tmp_path, simulate_sphere):
    data = tmp_path / "data"
    simulate_sphere(data)
    train = subprocess.run(
        [
            str(BIN / "ns-train"),
            "gaussian-atoms",
            "--machine.device-type",
            "cpu",
            "--vis",
            "tensorboard",
            "--output-dir",
            str(tmp_path / "out"),
            "--experiment-name",
            "v",
            "--timestamp",
            "run",
            "--max-num-iterations",
            "600",
            "tilt-series",
            "--data",
            str(data),
        ],
        capture_output=True,
        text=True,
    )
    assert train.returncode == 0, train.stderr[-2000:]
    png = tmp_path / "viewer.png"
    fraction = viewer_screenshot.screenshot(
        tmp_path / "out" / "v" / "gaussian-atoms" / "run" / "config.yml", png, wait_s=20.0
    )
    log = png.with_suffix(".log").read_text()
    assert "Traceback" not in log, log[-3000:]
    # 55 atoms drawn as viridis discs fill a few percent of a 1280 x 800 page (2-4% measured);
    # without them (a failed render or scene) the page has none of those colours.
    assert fraction > 0.005, f"atoms not visible: {fraction}"
