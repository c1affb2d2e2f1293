"""``/docs`` works offline: the page and every asset it loads come from the service itself."""

from __future__ import annotations

import fnmatch
import re
import tomllib
from html.parser import HTMLParser
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from randt.service.api.docs import SWAGGER_UI_VERSION
from randt.service.app import create_app
from randt.service.settings import ServiceSettings

ROOT = Path(__file__).resolve().parents[2]
CONTENT_TYPES = {".js": "text/javascript", ".css": "text/css", ".png": "image/png"}


class _Assets(HTMLParser):
    """Every ``<script src>`` and ``<link href>`` of a page."""

    def __init__(self) -> None:
        super().__init__()
        self.urls: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        wanted = {"script": "src", "link": "href"}.get(tag)
        self.urls += [v for k, v in attrs if k == wanted and v is not None]


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> TestClient:
    app = create_app(ServiceSettings(data_dir=tmp_path_factory.mktemp("docs")), with_zenoh=False)
    return TestClient(app)


def test_docs_load_only_local_assets(client: TestClient) -> None:
    page = client.get("/docs")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert "SwaggerUIBundle" in page.text and "url: '/openapi.json'" in page.text
    assert not re.search(r"https?://", page.text), "the page names no outside URL"
    parser = _Assets()
    parser.feed(page.text)
    assert sorted(Path(u).suffix for u in parser.urls) == [".css", ".js", ".png"]
    for url in parser.urls:
        assert url.startswith("/static/vendor/swagger-ui/"), url
        r = client.get(url)
        assert r.status_code == 200, url
        assert r.headers["content-type"].split(";")[0] == CONTENT_TYPES[Path(url).suffix], url
        vendored = ROOT / "service" / url.removeprefix("/")
        assert r.content == vendored.read_bytes(), url
        if url.endswith(".js"):
            assert f'PACKAGE_VERSION:"{SWAGGER_UI_VERSION}"' in r.text, "the pinned version is served"
    assert client.get("/openapi.json").json()["info"]["title"] == "randt-fleet"
    assert client.get("/redoc").status_code == 404, "ReDoc would load from a CDN: not served"


def test_docs_assets_ship_in_the_package() -> None:
    """pyproject's package-data covers the vendored files (an installed service serves them too)."""
    patterns = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    vendored = sorted((ROOT / "service/static/vendor/swagger-ui").iterdir())
    assert {p.name for p in vendored} >= {"swagger-ui-bundle.js", "swagger-ui.css", "LICENSE", "NOTICE"}
    for path in vendored:
        rel = path.relative_to(ROOT / "service").as_posix()
        assert any(fnmatch.fnmatch(rel, pat) for pat in patterns["randt.service"]), rel
