"""The map viewer in headless Chromium (the system's, driven by Playwright: tests/service/browser.py).

After a small simulated fleet has run, one of its sessions closed, the page must have loaded every
tile of the ``default`` map (several at a time, the table listing them as they arrive) and both
vehicles' trajectories (the finished one's too), draw a non-blank point cloud (checked on a
screenshot's pixels), fetch nothing from outside the service (it works offline), and log no
console errors.

Without Chromium the test skips with the reason; with ``CI=true`` it fails instead (``.ci/run``
installs it), as ``tests/data.py`` does for the real data.
"""

from __future__ import annotations

import io
import os
import time
from pathlib import Path

import numpy as np
import pytest

from tests.service.api_server import drive_fleet, live_server
from tests.service.browser import chromium_page, require_chromium

BACKGROUND_RGB = np.array([0x10, 0x14, 0x18])  # renderer.setClearColor in viewer.js
PANEL_WIDTH_PX = 330  # the side panel covers the canvas's left edge


def _drawn_fraction(png: bytes) -> tuple[float, int]:
    """Share of the canvas (right of the panel) not in the background colour, and distinct colours."""
    from PIL import Image

    rgb = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int16)[:, PANEL_WIDTH_PX:]
    drawn = np.abs(rgb - BACKGROUND_RGB).sum(axis=2) > 40
    colours = np.unique(rgb[drawn].reshape(-1, 3), axis=0)
    return float(drawn.mean()), int(colours.shape[0])


def test_viewer_draws_the_fleet_map_without_console_errors(tmp_path) -> None:
    binary = require_chromium()
    with live_server(tmp_path / "data") as server:
        fleet = drive_fleet(server.service)
        assert server.service.sessions.close("sim001", fleet.session)  # a finished session stays drawn
        # Closing folds the session's last points (those waiting for a map agreement check) into
        # the live map; the API serves tiles once saved (durable first): without this flush the
        # viewer listed 128 tiles against the live map's 131 in one run of three (and in CI).
        graph = server.service.sessions.graph
        assert graph is None or graph.wait_idle(120)  # (and no re-fold while the page loads)
        server.service.sessions.flush()
        grid = server.service.sessions.maps["default"]
        with chromium_page(binary) as seen:
            page = seen.page
            page.goto(server.url + "/")
            page.wait_for_function("() => window.randtViewer && window.randtViewer.ready", timeout=60_000)
            page.wait_for_function(
                "() => window.randtViewer.vehicles === 2 && window.randtViewer.trajectoryPoses",
                timeout=60_000,
            )
            viewer = page.evaluate("() => window.randtViewer")
            assert viewer["tiles"] == len(grid) and viewer["points"] == grid.n_points
            assert viewer["trajectoryPoses"] == sum(len(fleet.scans[v]) for v in ("sim000", "sim001"))
            assert viewer["finishedVehicles"] == 1
            # tiles come several at a time, and the table lists them while the rest still arrive
            assert len(grid) > 6 and viewer["maxInFlight"] == 6, viewer
            assert 0 < viewer["rowsWhileLoading"] < len(grid), viewer
            assert viewer["errors"] == []
            assert page.locator("#map-select").input_value() == "default"
            assert page.locator("#tiles tbody tr").count() == len(grid)
            vehicles = page.locator("#vehicles").inner_text()
            assert "sim000/drive1" in vehicles and "sim001/drive1" in vehicles
            assert "closed" in next(line for line in vehicles.splitlines() if "sim001/drive1" in line)

            time.sleep(0.5)  # a few animation frames after the last geometry update
            png = page.screenshot()
            (tmp_path / "viewer-height.png").write_bytes(png)
            drawn, colours = _drawn_fraction(png)
            assert drawn > 0.02, f"the canvas is (almost) blank: {drawn:.4f} of it drawn"
            assert colours > 50, f"only {colours} colours: not a height-coloured cloud"

            page.select_option("#color-select", "density")
            time.sleep(0.5)
            png = page.screenshot()
            (tmp_path / "viewer-density.png").write_bytes(png)
            assert _drawn_fraction(png)[0] > 0.02
            if os.environ.get("RANDT_VIEWER_SCREENSHOT"):  # for a person to look at
                Path(os.environ["RANDT_VIEWER_SCREENSHOT"]).write_bytes(
                    (tmp_path / "viewer-height.png").read_bytes()
                )

            # offline: every request the page made went to the service itself, and none failed
            assert seen.requests and seen.off_origin(server.url) == [], seen.requests
            assert any(u.endswith("/static/vendor/three/three.module.js") for u in seen.requests)
            assert seen.failures == []
            assert seen.console_errors == []


def test_docs_page_renders_offline(tmp_path) -> None:
    """``/docs`` in a browser: Swagger UI draws every operation of the schema from local assets."""
    binary = require_chromium()
    with live_server(tmp_path / "data") as server, chromium_page(binary) as seen:
        page = seen.page
        page.goto(server.url + "/docs")
        n_operations = sum(
            len(methods)
            for methods in page.evaluate("() => fetch('/openapi.json').then(r => r.json())")["paths"].values()
        )
        page.wait_for_function(
            f"() => document.querySelectorAll('.opblock').length === {n_operations}", timeout=60_000
        )
        assert "randt-fleet" in page.locator(".title").first.inner_text()
        assert seen.off_origin(server.url) == [], seen.requests
        assert any(u.endswith("/static/vendor/swagger-ui/swagger-ui-bundle.js") for u in seen.requests)
        assert seen.failures == [] and seen.console_errors == []


def test_without_chromium_ci_fails_and_a_developer_skips(monkeypatch: pytest.MonkeyPatch, tmp_path) -> None:
    monkeypatch.setenv("RANDT_CHROMIUM", str(tmp_path / "no-chromium-here"))
    monkeypatch.setenv("CI", "true")
    with pytest.raises(pytest.fail.Exception, match="needs chromium"):
        require_chromium()
    monkeypatch.delenv("CI")
    with pytest.raises(pytest.skip.Exception, match="needs chromium"):
        require_chromium()
