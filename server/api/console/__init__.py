"""The operator's console at ``/ui`` and the offline OpenAPI pages.

``install_console(app)`` adds, on an app created with ``docs_url=None, redoc_url=None``:
``/docs`` and ``/redoc`` from packaged bundles (docs.py); the console page ``/ui`` with
its script and styles (``static/``, plain HTML + one script, no build step) and the
Plotly bundle from the ``plotly`` package (``/ui/vendor/plotly.min.js``); the console's
JSON routes (routes.py); the board of live vehicles the stream reports to (live.py).
The page and its assets hold no data and need no key; every API call it makes sends the
key the operator signed in with (``X-API-Key``).
"""

from __future__ import annotations

from importlib.util import find_spec
from pathlib import Path

from fastapi import APIRouter, FastAPI
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles

from monoloc.server.api.console.docs import install_docs
from monoloc.server.api.console.live import vehicle_board
from monoloc.server.api.console.routes import router as console_api

STATIC_DIR = Path(__file__).with_name("static")
UI_ASSETS_URL = "/ui/assets"
PLOTLY_URL = "/ui/vendor/plotly.min.js"


def plotly_bundle() -> Path:
    """plotly.js as the ``plotly`` package ships it (found without importing it)."""
    spec = find_spec("plotly")
    if spec is None or not spec.submodule_search_locations:
        raise RuntimeError("the 'plotly' package is missing: pip install 'monoloc[server]'")
    return Path(next(iter(spec.submodule_search_locations))) / "package_data" / "plotly.min.js"


def install_console(app: FastAPI) -> None:
    install_docs(app)
    app.include_router(console_api)
    vehicle_board(app)
    pages = APIRouter(include_in_schema=False)
    bundle = plotly_bundle()

    @pages.get("/ui")
    def console_page() -> FileResponse:
        return FileResponse(STATIC_DIR / "index.html", headers={"Cache-Control": "no-cache"})

    @pages.get(PLOTLY_URL)
    def plotly_js() -> FileResponse:
        return FileResponse(bundle, media_type="text/javascript")

    app.include_router(pages)
    app.mount(UI_ASSETS_URL, StaticFiles(directory=STATIC_DIR), name="console-assets")
