"""The map viewer: ``/`` serves ``service/static/index.html``, ``/static/*`` its scripts.

The page is plain ES modules with no build step; three.js (MIT) is vendored under
``service/static/vendor/three/`` so the viewer works offline. The static files ship inside the
package (``pyproject.toml``: package data), found next to this module, never from the client's
path: Starlette's :class:`~starlette.staticfiles.StaticFiles` refuses paths outside its directory.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter, FastAPI
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles

__all__ = ["STATIC_DIR", "mount_viewer", "router"]

STATIC_DIR = Path(__file__).resolve().parent.parent / "static"

router = APIRouter(tags=["viewer"])


@router.get("/", response_class=FileResponse, include_in_schema=False)
def index() -> FileResponse:
    """The viewer page (data comes from the REST API, polled by the page)."""
    return FileResponse(
        STATIC_DIR / "index.html", media_type="text/html", headers={"Cache-Control": "no-cache"}
    )


def mount_viewer(app: FastAPI) -> None:
    """Add the page and its static files to ``app``."""
    app.include_router(router)
    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")
