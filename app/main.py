"""The HTTP API (FastAPI): registrations, models, operations endpoints and the admin page."""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI
from fastapi.staticfiles import StaticFiles
from starlette.datastructures import MutableHeaders
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app import problems
from app.api.routes import admin, health, models, registrations
from app.metrics import RequestMetrics
from app.uploads import BodySizeLimit
from core.config import get_settings
from vehicle_pose import __version__

DESCRIPTION = """
Register a vehicle's 3D model onto a photo: POST the photo and a model id, poll the job,
fetch the pose (camera K, R, t; the paper's theta; BOP fields) and an overlay image.
Authenticate with `Authorization: Bearer <API key>`. Errors are RFC 9457 problem details
(`application/problem+json`) whose `type` is stable.
"""


# The admin page is plain HTML and CSS from this origin: nothing else may load, frame or sniff it.
ADMIN_CSP = ("default-src 'none'; style-src 'self'; img-src 'self'; form-action 'self'; frame-ancestors 'none'; "
             "base-uri 'none'")


class SecurityHeaders:
    """``nosniff``, no framing and no referrer on every response; a strict CSP on the admin
    pages (a pure ASGI middleware: it touches only the response's start message)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        admin = scope["path"].startswith(("/admin", "/static"))

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = MutableHeaders(scope=message)
                headers.setdefault("X-Content-Type-Options", "nosniff")
                headers.setdefault("X-Frame-Options", "DENY")
                headers.setdefault("Referrer-Policy", "no-referrer")
                if admin:
                    headers.setdefault("Content-Security-Policy", ADMIN_CSP)
            await send(message)

        await self.app(scope, receive, send_with_headers)


def _local_docs(app: FastAPI) -> None:
    from fastapi.openapi.docs import get_swagger_ui_html
    from fastapi.responses import HTMLResponse
    from swagger_ui_bundle import swagger_ui_path

    app.mount("/docs-static", StaticFiles(directory=str(swagger_ui_path)), name="docs-static")

    @app.get("/docs", include_in_schema=False)
    def docs() -> HTMLResponse:
        return get_swagger_ui_html(
            openapi_url=app.openapi_url or "/openapi.json", title="vehicle-pose API",
            swagger_js_url="/docs-static/swagger-ui-bundle.js", swagger_css_url="/docs-static/swagger-ui.css",
            swagger_favicon_url="/docs-static/favicon-32x32.png",
        )


def create_app() -> FastAPI:
    settings = get_settings()
    # The interactive docs are served from this machine (swagger-ui-bundle), not from a CDN, so
    # they work offline and behind a firewall.
    app = FastAPI(title="vehicle-pose", version=__version__, description=DESCRIPTION, docs_url=None, redoc_url=None)
    problems.install(app)
    _local_docs(app)
    app.include_router(registrations.router)
    app.include_router(models.router)
    app.include_router(health.router)
    app.include_router(admin.router)
    app.mount("/static", StaticFiles(directory=Path(__file__).resolve().parent / "static"), name="static")

    def limit_for(path: str) -> int | None:
        if path.startswith("/v1/models"):
            return settings.max_mesh_bytes
        if path.startswith("/v1/"):
            return settings.max_upload_bytes
        return None

    app.add_middleware(BodySizeLimit, limit_for=limit_for, timeout_s=settings.body_timeout_s)
    app.add_middleware(RequestMetrics)
    app.add_middleware(SecurityHeaders)
    return app

