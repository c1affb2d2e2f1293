"""The map viewer in headless Chromium (Debian's ``chromium`` + ``chromium-driver``, via selenium).

After a small simulated fleet has run, the page must have loaded every tile of the ``default`` map
and both vehicles' trajectories, draw a non-blank point cloud (checked on a screenshot's pixels),
fetch nothing from outside the service (it works offline), and log no console errors.

Without Chromium the test skips with the reason; with ``CI=true`` it fails instead (``.ci/run``
installs the packages), as ``tests/data.py`` does for the real data.
"""

from __future__ import annotations

import io
import os
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from tests.service.api_server import drive_fleet, live_server

CHROMIUM_CANDIDATES = ("/usr/bin/chromium", "/usr/bin/chromium-browser")
CHROMEDRIVER = "/usr/bin/chromedriver"
BACKGROUND_RGB = np.array([0x10, 0x14, 0x18])  # renderer.setClearColor in viewer.js
PANEL_WIDTH_PX = 330  # the side panel covers the canvas's left edge


def _require_chromium() -> str:
    binary = next((c for c in CHROMIUM_CANDIDATES if Path(c).is_file()), shutil.which("chromium"))
    missing = []
    if binary is None:
        missing.append("chromium")
    if not Path(CHROMEDRIVER).is_file():
        missing.append("chromium-driver")
    try:
        import selenium  # noqa: F401
    except ImportError:
        missing.append("selenium (pip install -e '.[test]')")
    if missing:
        message = (
            f"headless Chromium test needs {', '.join(missing)} (Debian: apt-get install chromium "
            "chromium-driver; .ci/run installs them)"
        )
        if os.environ.get("CI") == "true":
            pytest.fail(message, pytrace=False)
        pytest.skip(message)
    return binary


def _browser(binary: str):
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service as ChromeService

    options = webdriver.ChromeOptions()
    options.binary_location = binary
    for arg in (
        "--headless=new",
        "--no-sandbox",  # CI runs as root
        "--disable-dev-shm-usage",
        "--window-size=1280,800",
        "--enable-unsafe-swiftshader",  # WebGL on the CPU: no GPU on the machine
        "--use-angle=swiftshader",
        "--ignore-gpu-blocklist",
    ):
        options.add_argument(arg)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    # An explicit driver path: selenium never tries to download one.
    return webdriver.Chrome(service=ChromeService(executable_path=CHROMEDRIVER), options=options)


def _wait_for(driver, script: str, timeout: float = 60.0) -> object:
    deadline = time.monotonic() + timeout
    value = None
    while time.monotonic() < deadline:
        value = driver.execute_script(script)
        if value:
            return value
        time.sleep(0.25)
    raise AssertionError(f"timed out waiting for {script!r} (last value {value!r})")


def _drawn_fraction(png: bytes) -> tuple[float, int]:
    """Share of the canvas (right of the panel) not in the background colour, and distinct colours."""
    from PIL import Image

    rgb = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int16)[:, PANEL_WIDTH_PX:]
    drawn = np.abs(rgb - BACKGROUND_RGB).sum(axis=2) > 40
    colours = np.unique(rgb[drawn].reshape(-1, 3), axis=0)
    return float(drawn.mean()), int(colours.shape[0])


def test_viewer_draws_the_fleet_map_without_console_errors(tmp_path) -> None:
    binary = _require_chromium()
    with live_server(tmp_path / "data") as server:
        fleet = drive_fleet(server.service)
        grid = server.service.sessions.maps["default"]
        driver = _browser(binary)
        try:
            driver.get(server.url + "/")
            _wait_for(driver, "return window.randtViewer && window.randtViewer.ready")
            _wait_for(
                driver, "return window.randtViewer.vehicles === 2 && window.randtViewer.trajectoryPoses"
            )
            viewer = driver.execute_script("return window.randtViewer")
            assert viewer["tiles"] == len(grid) and viewer["points"] == grid.n_points
            assert viewer["trajectoryPoses"] == sum(len(fleet.scans[v]) for v in ("sim000", "sim001"))
            assert viewer["errors"] == []
            assert driver.find_element("id", "map-select").get_attribute("value") == "default"
            rows = driver.find_elements("css selector", "#tiles tbody tr")
            assert len(rows) == len(grid)
            vehicles = driver.find_element("id", "vehicles").text
            assert "sim000/drive1" in vehicles and "sim001/drive1" in vehicles

            time.sleep(0.5)  # a few animation frames after the last geometry update
            png = driver.get_screenshot_as_png()
            (tmp_path / "viewer-height.png").write_bytes(png)
            drawn, colours = _drawn_fraction(png)
            assert drawn > 0.02, f"the canvas is (almost) blank: {drawn:.4f} of it drawn"
            assert colours > 50, f"only {colours} colours: not a height-coloured cloud"

            driver.execute_script(
                "const s = document.getElementById('color-select');"
                "s.value = 'density'; s.dispatchEvent(new Event('change'));"
            )
            time.sleep(0.5)
            png = driver.get_screenshot_as_png()
            (tmp_path / "viewer-density.png").write_bytes(png)
            assert _drawn_fraction(png)[0] > 0.02
            if os.environ.get("RANDT_VIEWER_SCREENSHOT"):  # for a person to look at
                Path(os.environ["RANDT_VIEWER_SCREENSHOT"]).write_bytes(
                    (tmp_path / "viewer-height.png").read_bytes()
                )

            # offline: every resource the page loaded came from the service itself
            urls = driver.execute_script(
                "return performance.getEntriesByType('resource').map(e => e.name).concat([location.href])"
            )
            assert urls and all(u.startswith(server.url) for u in urls), urls
            assert any(u.endswith("/static/vendor/three/three.module.js") for u in urls)

            logs = driver.get_log("browser")
            errors = [e for e in logs if e["level"] == "SEVERE"]
            assert errors == [], errors
        finally:
            driver.quit()
