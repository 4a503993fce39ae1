"""The HTTP API (FastAPI): registrations, models, operations endpoints and the admin page."""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI
from fastapi.staticfiles import StaticFiles

from vehicle_pose import __version__

from .api.routes import admin, health, models, registrations
from .core import problems
from .core.config import get_settings
from .core.metrics import RequestMetrics
from .uploads import BodySizeLimit

DESCRIPTION = """
Register a vehicle's 3D model onto a photo: POST the photo and a model id, poll the job,
fetch the pose (camera K, R, t; the paper's theta; BOP fields) and an overlay image.
Authenticate with `Authorization: Bearer <API key>`. Errors are RFC 9457 problem details
(`application/problem+json`) whose `type` is stable.
"""


def create_app() -> FastAPI:
    settings = get_settings()
    app = FastAPI(title="vehicle-pose", version=__version__, description=DESCRIPTION)
    problems.install(app)
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

    app.add_middleware(BodySizeLimit, limit_for=limit_for)
    app.add_middleware(RequestMetrics)
    return app


app = create_app()
