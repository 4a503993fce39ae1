"""/v1/registrations: submit a photo, poll the job, fetch the overlay and the photo."""

from __future__ import annotations

import logging
from typing import Annotated, Any, cast

from fastapi import APIRouter, Depends, File, Form, Header, Request, Response, UploadFile, status
from fastapi.responses import JSONResponse
from sqlalchemy.orm import Session

from app.api.deps import CurrentClient, SessionDep, SettingsDep
from app.problems import Problem
from app.registrations import (
    check_model,
    check_photo,
    create_job,
    find_idempotent,
    job_out,
    links,
    parse_hints,
    request_hash,
    stored_response,
    visible_job,
)
from app.schemas import RegistrationAccepted, RegistrationOut, Status
from core.models import JobStatus, Registration
from core.queue import PRIORITY_NEW, TASK, get_breaker, get_celery
from core.storage import get_storage

log = logging.getLogger(__name__)
router = APIRouter(prefix="/v1/registrations", tags=["registrations"])

_PROBLEM: dict[str, Any] = {"content": {"application/problem+json": {}}}


def _accepted(job: Registration) -> JSONResponse:
    body = RegistrationAccepted(id=job.id, status=cast(Status, job.status), links=links(job))
    return JSONResponse(body.model_dump(mode="json"), status_code=202, headers={"Location": body.links.self})


async def _each_field_once(request: Request) -> None:
    """422 for a form that sends a field twice (two photos, two cameras): which one the client
    meant is not for the service to guess."""
    form = await request.form()  # the form the endpoint's fields were read from (parsed once)
    twice = sorted({name for name in form if len(form.getlist(name)) > 1})
    if twice:
        raise Problem(422, "duplicate-field", f"the form sends {', '.join(twice)} more than once")


@router.post(
    "",
    status_code=status.HTTP_202_ACCEPTED,
    response_model=RegistrationAccepted,
    responses={code: _PROBLEM for code in (401, 409, 413, 415, 422, 503)},
    dependencies=[Depends(_each_field_once)],
)
def submit(
    client: CurrentClient,
    session: SessionDep,
    settings: SettingsDep,
    photo: Annotated[UploadFile, File(description="the vehicle photo (JPEG, PNG, HEIC/HEIF, AVIF, WebP, TIFF or BMP)")],
    model_id: Annotated[
        str,
        Form(description="id of a model from GET /v1/models; a,b,c to identify the model among these; "
                         "auto to identify it among every model"),
    ],
    init_camera: Annotated[str | None, Form(description="start camera JSON {K, R, t, width, height}")] = None,
    bbox: Annotated[str | None, Form(description="vehicle box X0,Y0,X1,Y1 in pixels")] = None,
    options: Annotated[str | None, Form(description="engine options JSON, see RegistrationOptionsIn")] = None,
    idempotency_key: Annotated[str | None, Header(max_length=200)] = None,
) -> JSONResponse:
    """Queue a registration; answers 202 with the job's URL at once."""
    model_id = check_model(model_id)
    data = photo.file.read()
    checked = check_photo(data, settings)
    hints = parse_hints(init_camera, bbox, options, checked)
    fingerprint = request_hash(data, model_id, hints)
    if idempotency_key:
        existing = find_idempotent(session, client, idempotency_key, fingerprint)
        if existing is not None and existing.never_queued:
            # The first try answered 503 "try again": this is that retry, so queue the job now.
            existing.requeue_submission()
            session.commit()
            _enqueue(session, existing.id)
        if existing is not None:
            return _accepted(existing)
    job, created = create_job(session, get_storage(), client, model_id, checked, hints, idempotency_key, fingerprint)
    if created:
        _enqueue(session, job.id)
    return _accepted(job)


def _enqueue(session: Session, job_id: str) -> None:
    """Send the job to the queue; if the broker is down the job is marked failed, never left queued."""
    try:
        # No publish retries: the broker's socket timeouts bound the wait, and the client is told
        # to try again (a retry with the same Idempotency-Key queues this same job); while the
        # broker is known to be down, the breaker answers at once.
        get_breaker().send(get_celery(), TASK, args=[job_id], task_id=job_id, priority=PRIORITY_NEW)
    except Exception as exc:  # kombu raises many connection error types; BrokerDown
        log.error("cannot queue job %s: %s", job_id, exc)
        job = session.get(Registration, job_id)
        if job is not None:
            job.finish(JobStatus.failed, "broker-unavailable", "the job queue could not be reached at submission")
            session.commit()
        raise Problem(503, "broker-unavailable", "the job queue cannot be reached; try again") from None


@router.get("/{job_id}", response_model=RegistrationOut, responses={404: _PROBLEM})
def status_of(job_id: str, client: CurrentClient, session: SessionDep) -> RegistrationOut:
    """The job's status, its progress while running, its result when done."""
    return job_out(visible_job(session, client, job_id))


@router.get("/{job_id}/overlay.png", response_class=Response,
            responses={200: {"content": {"image/png": {}}}, 404: _PROBLEM})
def overlay(job_id: str, client: CurrentClient, session: SessionDep) -> Response:
    """The registered model's outline drawn on the photo (PNG, at most 2048 px on its longer side), once the
    job succeeded."""
    return stored_response(visible_job(session, client, job_id).overlay_key, "image/png", "overlay")


@router.get("/{job_id}/parts.png", response_class=Response,
            responses={200: {"content": {"image/png": {}}}, 404: _PROBLEM})
def parts(job_id: str, client: CurrentClient, session: SessionDep) -> Response:
    """The part map at the registered pose: an indexed PNG of the photo's size, each pixel the label of the
    car's part it shows (0: none); the palette holds the parts' colours and the ``legend`` text chunk maps
    part ids to labels. The job's ``result.parts`` lists the visible parts."""
    return stored_response(visible_job(session, client, job_id).parts_key, "image/png", "part map")


@router.get("/{job_id}/photo", response_class=Response, responses={200: {"content": {"image/*": {}}}, 404: _PROBLEM})
def photo_of(job_id: str, client: CurrentClient, session: SessionDep) -> Response:
    """The photo as uploaded."""
    job = visible_job(session, client, job_id)
    return stored_response(job.photo_key, job.photo_media_type, "photo")
