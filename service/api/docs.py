"""``/docs``: the interactive OpenAPI page, with Swagger UI served by the service itself.

FastAPI's own ``/docs`` loads Swagger UI from a CDN, so without the internet (a vehicle depot's
network) it shows a blank page. The app factory turns it off (``docs_url=None``, and ReDoc,
which has the same problem, with ``redoc_url=None``); this route renders the same page from the
vendored copy under ``service/static/vendor/swagger-ui/`` (``README.md`` there: version, licence,
how to update), mounted with the viewer's static files at ``/static``.
"""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse

__all__ = ["SWAGGER_UI_VERSION", "router"]

#: The vendored ``swagger-ui-dist`` (``service/static/vendor/swagger-ui/README.md``).
SWAGGER_UI_VERSION = "5.35.0"

_ASSETS = "/static/vendor/swagger-ui"

router = APIRouter(tags=["docs"])


@router.get("/docs", response_class=HTMLResponse, include_in_schema=False)
def swagger_ui(request: Request) -> HTMLResponse:
    """The Swagger UI page for ``/openapi.json``, every asset from this service."""
    root = request.scope.get("root_path", "").rstrip("/")
    return get_swagger_ui_html(
        openapi_url=f"{root}{request.app.openapi_url}",
        title=f"{request.app.title} - API docs",
        swagger_js_url=f"{root}{_ASSETS}/swagger-ui-bundle.js",
        swagger_css_url=f"{root}{_ASSETS}/swagger-ui.css",
        swagger_favicon_url=f"{root}{_ASSETS}/favicon-32x32.png",
        # no "valid" badge fetched from validator.swagger.io
        swagger_ui_parameters={"validatorUrl": None},
    )
