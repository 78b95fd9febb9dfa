"""Screenshot of nerfstudio's viewer showing a finished run's atoms, in headless Chromium.

Starts ``ns-viewer --load-config RUN/config.yml`` on a free port, opens the viewer page in
headless Chromium (Selenium with Debian's chromium and chromium-driver; WebGL through
SwiftShader, no GPU needed), waits for the scene, and saves a PNG.  Exit status 0 only if the
screenshot shows the atoms: enough pixels in the viridis colours of the atom point cloud.

    gaussian-atoms screenshot --load-config RUN/config.yml --output viewer.png

Needs: ``apt-get install chromium chromium-driver`` and ``pip install selenium``.
"""

from __future__ import annotations

import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np


def chromium_paths() -> tuple[str, str] | None:
    """(browser, driver) paths, or None when either is missing."""
    browser = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
    driver = shutil.which("chromedriver")
    return (browser, driver) if browser and driver else None


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for_http(url: str, timeout_s: float, process: subprocess.Popen) -> None:
    deadline = time.time() + timeout_s
    while time.time() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"ns-viewer exited with status {process.returncode} before serving {url}")
        try:
            urllib.request.urlopen(url, timeout=2).read(1)
            return
        except OSError:
            time.sleep(1.0)
    raise TimeoutError(f"ns-viewer did not serve {url} within {timeout_s:.0f} s")


def atom_pixel_fraction(png: Path) -> float:
    """Fraction of pixels close to a viridis colour (the atoms), away from greys and white."""
    from matplotlib import colormaps
    from PIL import Image

    rgb = np.asarray(Image.open(png).convert("RGB"), dtype=np.float64)
    palette = colormaps["viridis"](np.linspace(0.0, 1.0, 64))[:, :3] * 255
    pixels = rgb.reshape(-1, 3)
    saturated = (pixels.max(axis=1) - pixels.min(axis=1)) > 40  # not grey / white UI
    distance = (
        np.min(np.linalg.norm(pixels[saturated, None, :] - palette[None], axis=-1), axis=1)
        if saturated.any()
        else np.zeros(0)
    )
    return float(np.sum(distance < 25) / len(pixels))


def screenshot(config: Path, output: Path, wait_s: float = 25.0, size=(1280, 800)) -> float:
    """Save the viewer's page as a PNG; returns the fraction of atom-coloured pixels."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    paths = chromium_paths()
    if paths is None:
        raise RuntimeError("headless Chromium not found: apt-get install chromium chromium-driver")
    port = free_port()
    log = open(output.with_suffix(".log"), "w")  # the viewer's own output, for when it fails
    viewer = subprocess.Popen(
        [
            str(Path(sys.executable).parent / "ns-viewer"),
            "--load-config",
            str(config),
            "--viewer.websocket-port",
            str(port),
        ],
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    try:
        url = f"http://localhost:{port}"
        wait_for_http(url, 180.0, viewer)
        options = webdriver.ChromeOptions()
        options.binary_location = paths[0]
        for flag in (
            "--headless=new",
            "--no-sandbox",
            "--disable-dev-shm-usage",
            "--use-angle=swiftshader",
            "--enable-unsafe-swiftshader",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--no-first-run",
            f"--window-size={size[0]},{size[1]}",
        ):
            options.add_argument(flag)
        driver = webdriver.Chrome(service=Service(paths[1]), options=options)
        try:
            driver.get(url)
            time.sleep(wait_s)  # websocket connect, scene and point cloud sent, first renders
            output.parent.mkdir(parents=True, exist_ok=True)
            driver.save_screenshot(str(output))
        finally:
            driver.quit()
    finally:
        viewer.terminate()
        try:
            viewer.wait(timeout=20)
        except subprocess.TimeoutExpired:
            viewer.kill()
        log.close()
    return atom_pixel_fraction(output)
