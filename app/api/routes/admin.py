"""/admin: a server-rendered page of recent registrations, filterable, with a detail view."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Query, Request, Response
from fastapi.responses import HTMLResponse
from fastapi.templating import Jinja2Templates
from sqlalchemy import func, select

from app.api.deps import AdminClient, SessionDep, SettingsDep
from app.problems import Problem
from app.registrations import BROWSER_TYPES, stored_response, viewable_photo, visible_job
from core.library import get_library
from core.models import Client, JobStatus, Registration
from vehicle_pose.model.parts import COLOURS

router = APIRouter(prefix="/admin", tags=["admin"], include_in_schema=False)
templates = Jinja2Templates(directory=Path(__file__).resolve().parents[2] / "templates")
PER_PAGE = 20


@router.get("", response_class=HTMLResponse)
def recent(
    request: Request,
    admin: AdminClient,
    session: SessionDep,
    status: Annotated[str | None, Query()] = None,
    model: Annotated[str | None, Query()] = None,
    page: Annotated[int, Query(ge=1, le=1_000_000)] = 1,
) -> HTMLResponse:
    """Recent registrations, newest first."""
    status = status or None
    model = model or None
    if status is not None and status not in {s.value for s in JobStatus}:
        raise Problem(422, "validation-error", f"unknown status {status!r}")
    query = select(Registration)
    if status:
        query = query.where(Registration.status == status)
    if model:
        query = query.where(Registration.model_id == model)
    total = session.scalar(select(func.count()).select_from(query.subquery())) or 0
    pages = max(1, math.ceil(total / PER_PAGE))
    jobs = session.scalars(
        query.order_by(Registration.created_at.desc(), Registration.id).offset((page - 1) * PER_PAGE).limit(PER_PAGE)
    ).all()
    models = sorted(set(get_library().ids()) | set(session.scalars(select(Registration.model_id).distinct())))
    return templates.TemplateResponse(
        request,
        "admin_list.html",
        {
            "jobs": jobs,
            "status": status,
            "model": model,
            "page": page,
            "pages": pages,
            "total": total,
            "statuses": [s.value for s in JobStatus],
            "models": models,
            "admin": admin,
            "clients": session.scalar(select(func.count()).select_from(Client)),
        },
    )


@router.get("/registrations/{job_id}", response_class=HTMLResponse)
def detail(request: Request, job_id: str, admin: AdminClient, session: SessionDep) -> HTMLResponse:
    """One registration: photo, overlay (the parts in colours), the parts' legend and the pose JSON."""
    job = visible_job(session, admin, job_id)
    pose = json.dumps(job.result, indent=2) if job.result else None
    parts = [dict(p, colour="#{:02x}{:02x}{:02x}".format(*COLOURS.get(p["part"], (0, 0, 0))))
             for p in (job.result or {}).get("parts", [])]
    # A photo in a type the browser does not show (a phone's HEIC, a TIFF) is shown as a JPEG.
    shown = "photo" if job.photo_media_type in BROWSER_TYPES else "photo.jpg"
    return templates.TemplateResponse(request, "admin_detail.html",
                                      {"job": job, "pose": pose, "parts": parts, "photo_view": shown})


@router.get("/registrations/{job_id}/thumbnail.jpg")
def thumbnail(job_id: str, admin: AdminClient, session: SessionDep) -> Response:
    return stored_response(visible_job(session, admin, job_id).thumbnail_key, "image/jpeg", "thumbnail")


@router.get("/registrations/{job_id}/overlay.png")
def overlay(job_id: str, admin: AdminClient, session: SessionDep) -> Response:
    return stored_response(visible_job(session, admin, job_id).overlay_key, "image/png", "overlay")


@router.get("/registrations/{job_id}/parts.png")
def parts(job_id: str, admin: AdminClient, session: SessionDep) -> Response:
    return stored_response(visible_job(session, admin, job_id).parts_key, "image/png", "part map")


@router.get("/registrations/{job_id}/photo")
def photo(job_id: str, admin: AdminClient, session: SessionDep) -> Response:
    job = visible_job(session, admin, job_id)
    return stored_response(job.photo_key, job.photo_media_type, "photo")


@router.get("/registrations/{job_id}/photo.jpg")
def photo_jpeg(job_id: str, admin: AdminClient, session: SessionDep, settings: SettingsDep) -> Response:
    """The photo as a JPEG a browser shows (upright, at most 1600 pixels), whatever its type."""
    return viewable_photo(visible_job(session, admin, job_id), settings)
