"""Headless Chromium for the page tests, driven over the DevTools protocol by Playwright.

Playwright talks to the browser directly (no chromedriver) and is pointed at the system's
Chromium (``executable_path``): nothing is downloaded. A :class:`Page` records every request the
page makes, every failed or refused one, and every console error and uncaught exception, so a test
can say the page worked offline and logged nothing bad.

Without Chromium (or Playwright: the test extra) a test skips with the reason; with ``CI=true`` it
fails instead (``.ci/run`` installs Chromium), as ``tests/data.py`` does for the real data.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

#: Where Debian and Ubuntu put Chromium; ``RANDT_CHROMIUM`` names another binary.
CHROMIUM_CANDIDATES = ("/usr/bin/chromium", "/usr/bin/chromium-browser")
CHROMIUM_ENV_VAR = "RANDT_CHROMIUM"

_ARGS = (
    "--no-sandbox",  # CI runs as root
    "--disable-dev-shm-usage",
    "--enable-unsafe-swiftshader",  # WebGL on the CPU: no GPU on the machine
    "--use-angle=swiftshader",
    "--ignore-gpu-blocklist",
)


def require_chromium() -> str:
    """The Chromium binary to drive; skips (fails under ``CI=true``) when it or Playwright is missing."""
    given = os.environ.get(CHROMIUM_ENV_VAR)
    binary = given or next(
        (c for c in CHROMIUM_CANDIDATES if Path(c).is_file()),
        shutil.which("chromium") or shutil.which("chromium-browser"),
    )
    missing = []
    if binary is None or not Path(binary).is_file():
        missing.append(f"chromium (Debian: apt-get install chromium; or {CHROMIUM_ENV_VAR}=<binary>)")
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        missing.append("playwright (pip install -e '.[test]')")
    if missing:
        message = f"headless Chromium test needs {', '.join(missing)}; .ci/run installs them"
        if os.environ.get("CI") == "true":
            pytest.fail(message, pytrace=False)
        pytest.skip(message)
    assert binary is not None
    return binary


@dataclass
class Page:
    """A Playwright page and what it did: requests, failures, console errors."""

    page: Any  # playwright.sync_api.Page
    requests: list[str] = field(default_factory=list)
    failures: list[str] = field(default_factory=list)
    console_errors: list[str] = field(default_factory=list)

    def off_origin(self, origin: str) -> list[str]:
        """Requests that did not go to ``origin`` (``http://127.0.0.1:port``)."""
        return [u for u in self.requests if u != origin and not u.startswith(origin + "/")]


@contextmanager
def chromium_page(binary: str, width: int = 1280, height: int = 800) -> Iterator[Page]:
    """One headless Chromium page of ``width`` x ``height`` CSS pixels, recording what it does."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=binary, headless=True, args=list(_ARGS))
        try:
            page = browser.new_page(viewport={"width": width, "height": height})
            seen = Page(page)
            page.on("request", lambda r: seen.requests.append(r.url))
            page.on("requestfailed", lambda r: seen.failures.append(f"{r.url}: {r.failure}"))
            page.on(
                "response",
                lambda r: r.status >= 400 and seen.failures.append(f"{r.url}: HTTP {r.status}"),
            )
            page.on(
                "console",
                lambda m: m.type == "error" and seen.console_errors.append(f"{m.text} ({m.location})"),
            )
            page.on("pageerror", lambda exc: seen.console_errors.append(f"uncaught: {exc}"))
            yield seen
        finally:
            browser.close()
