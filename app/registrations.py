"""Creating registration jobs and presenting them; the routes stay thin around these."""

from __future__ import annotations

import hashlib
import json
import threading
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from pydantic import ValidationError
from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session
from starlette.responses import Response

from app.problems import Problem
from app.schemas import JobError, Links, Progress, RegistrationOptionsIn, RegistrationOut
from app.uploads import SNIFF_BYTES, sniff_image
from core.config import Settings
from core.library import get_library
from core.models import Client, JobStatus, Registration, as_utc, new_id
from core.storage import ObjectMissing, Storage, get_storage
from vehicle_pose import (
    Camera,
    CameraError,
    PhotoError,
    PhotoTooLargeError,
)
from vehicle_pose.errors import UnknownModelError
from vehicle_pose.model.library import AUTO
from vehicle_pose.photo import decode_photo, resized_within, verify_photo
from vehicle_pose.render.overlay import encode_image
from vehicle_pose.search.views import parse_bbox


@dataclass(frozen=True)
class Photo:
    data: bytes
    media_type: str
    width: int
    height: int


# Photos verified at once by one API process: a 156 KB PNG can declare 49 megapixels, and each
# verification holds its decoded image (JPEGs are verified at an eighth of their size).
_DECODING = threading.BoundedSemaphore(2)


def check_photo(data: bytes, settings: Settings) -> Photo:
    """The photo if the engine can use it: 415 for a non-image, 413 for a bomb, 422 if damaged."""
    media_type = sniff_image(data[:SNIFF_BYTES])
    if media_type is None:
        raise Problem(415, "unsupported-media-type",
                      "the photo is not a JPEG, PNG, HEIC/HEIF, AVIF, WebP, TIFF or BMP image")
    try:
        with _DECODING:
            width, height = verify_photo(data, max_pixels=settings.max_photo_pixels)
    except PhotoTooLargeError as exc:
        raise Problem(413, exc.code, str(exc)) from None
    except PhotoError as exc:
        raise Problem(422, exc.code, str(exc)) from None
    return Photo(data, media_type, width, height)


def parse_hints(
    init_camera: str | None, bbox: str | None, options: str | None, photo: Photo
) -> tuple[dict[str, Any] | None, list[float] | None, dict[str, Any]]:
    """Validated hints as stored in the job: camera JSON, box, engine options; 422 when malformed."""
    camera = None
    if init_camera:
        try:
            parsed = Camera.from_json(init_camera, what="init_camera")
            parsed.for_photo(photo.width, photo.height)
            camera = parsed.to_dict()
        except CameraError as exc:
            raise Problem(422, "invalid-camera", str(exc)) from None
    box = None
    if bbox:
        try:
            box = list(parse_bbox(bbox, photo.width, photo.height))
        except CameraError as exc:
            raise Problem(422, "invalid-bbox", str(exc)) from None
    opts: dict[str, Any] = {}
    if options:
        try:
            opts = RegistrationOptionsIn.model_validate_json(options).engine_kwargs()
        except ValidationError as exc:
            raise Problem(422, "invalid-options", "invalid options: " + _explain(exc)) from None
        except ValueError as exc:
            raise Problem(422, "invalid-options", str(exc).splitlines()[0] if str(exc) else "invalid options") from None
    return camera, box, opts


def _explain(exc: ValidationError) -> str:
    """Each error as ``field: reason`` (pydantic's own first line names only the model)."""
    parts = []
    for err in exc.errors(include_url=False)[:5]:
        where = ".".join(str(p) for p in err.get("loc", ())) or "options"
        given = err.get("input")
        shown = f", not {given!r}" if isinstance(given, (str, int, float, bool)) and len(repr(given)) <= 40 else ""
        parts.append(f"{where}: {err.get('msg', 'invalid')}{shown}")
    more = len(exc.errors()) - len(parts)
    return "; ".join(parts) + (f" (and {more} more)" if more > 0 else "")


def check_model(model_id: str) -> str:
    """The model field as kept: one id, ``a,b,c`` (spaces around the ids dropped) or ``auto``;
    422 before anything is stored or queued when an id is unknown or the field is too long."""
    if len(model_id) > 64:
        raise Problem(422, "unknown-model", "model_id must be at most 64 characters", model_id=model_id[:64])
    try:
        ids = get_library().resolve(model_id)
    except UnknownModelError as exc:
        raise Problem(422, "unknown-model", str(exc), model_id=model_id) from None
    return AUTO if model_id.strip() == AUTO else ",".join(ids)


def request_hash(photo: bytes, model_id: str,
                 hints: tuple[dict[str, Any] | None, list[float] | None, dict[str, Any]]) -> str:
    """Fingerprint of a request, to tell a retry from a different request reusing a key: the
    photo's bytes and the hints as parsed (so spacing, key order and number spelling in the
    client's JSON do not make a retry another request)."""
    h = hashlib.sha256(photo)
    h.update(b"\x00" + model_id.encode())
    h.update(b"\x00" + json.dumps(hints, sort_keys=True, separators=(",", ":")).encode())
    return h.hexdigest()


def find_idempotent(session: Session, client: Client, key: str, fingerprint: str) -> Registration | None:
    """The job created earlier with this Idempotency-Key; 409 if that request differed."""
    job = session.scalars(
        select(Registration).where(Registration.client_id == client.id, Registration.idempotency_key == key)
    ).first()
    if job is not None and job.request_hash != fingerprint:
        raise Problem(409, "idempotency-key-reused", "this Idempotency-Key was used for a different request")
    return job


def create_job(
    session: Session,
    storage: Storage,
    client: Client,
    model_id: str,
    photo: Photo,
    hints: tuple[dict[str, Any] | None, list[float] | None, dict[str, Any]],
    idempotency_key: str | None,
    fingerprint: str,
) -> tuple[Registration, bool]:
    """Store the photo and the job record; returns (job, created). The caller queues it."""
    job_id = new_id()
    photo_key = f"photos/{job_id}"
    storage.put(photo_key, photo.data, photo.media_type)
    camera, box, opts = hints
    job = Registration(
        id=job_id,
        client_id=client.id,
        idempotency_key=idempotency_key,
        request_hash=fingerprint,
        model_id=model_id,
        status=JobStatus.queued.value,
        photo_key=photo_key,
        photo_media_type=photo.media_type,
        photo_width=photo.width,
        photo_height=photo.height,
        init_camera=camera,
        bbox=box,
        options=opts,
    )
    session.add(job)
    try:
        session.commit()
    except IntegrityError:
        # A concurrent retry with the same Idempotency-Key won the race: answer with its job.
        session.rollback()
        storage.delete(photo_key)
        existing = find_idempotent(session, client, idempotency_key or "", fingerprint)
        if existing is None:
            raise
        return existing, False
    return job, True


def visible_job(session: Session, client: Client, job_id: str) -> Registration:
    """The job if this client may see it (its own, or any for an admin); 404 otherwise."""
    job = session.get(Registration, job_id) if len(job_id) <= 64 else None
    if job is None or (job.client_id != client.id and not client.is_admin):
        raise Problem(404, "not-found", f"no registration {job_id!r}")
    return job


_CACHED = {"Cache-Control": "private, max-age=3600"}  # a stored object or a rendition of one


def _stored(key: str | None, what: str) -> bytes:
    if key is None:
        raise Problem(404, "not-found", f"this registration has no {what} yet")
    try:
        return get_storage().get(key)
    except ObjectMissing:
        raise Problem(404, "not-found", f"the {what} is no longer stored") from None


def stored_response(key: str | None, media_type: str, what: str) -> Response:
    """The stored object under ``key`` as a response; 404 when there is none (yet, or any more)."""
    return Response(_stored(key, what), media_type=media_type, headers=_CACHED)


BROWSER_TYPES = frozenset(("image/jpeg", "image/png", "image/webp", "image/avif", "image/bmp"))
"""The photo types every current browser shows in an ``<img>``; TIFF and HEIC/HEIF are not."""

VIEW_SIZE = 1600
"""The longer side (pixels) of a photo's JPEG rendition (:func:`viewable_photo`)."""


def viewable_photo(job: Registration, settings: Settings) -> Response:
    """A JPEG of the registration's photo that a browser shows: upright (its EXIF orientation
    applied), its longer side at most :data:`VIEW_SIZE`; for a photo in a type a browser does not
    show (:data:`BROWSER_TYPES`: a phone's HEIC, a TIFF)."""
    data = _stored(job.photo_key, "photo")
    try:
        with _DECODING:
            rgb = decode_photo(data, max_pixels=settings.max_photo_pixels, reduce_to=VIEW_SIZE)
    except PhotoError as exc:  # it was verified on upload: only a damaged store gets here
        raise Problem(422, exc.code, str(exc)) from None
    jpeg = encode_image(resized_within(rgb, VIEW_SIZE), ".jpg", [cv2.IMWRITE_JPEG_QUALITY, 90])
    return Response(jpeg, media_type="image/jpeg", headers=_CACHED)


def links(job: Registration) -> Links:
    base = f"/v1/registrations/{job.id}"
    return Links(self=base, photo=f"{base}/photo", overlay=f"{base}/overlay.png" if job.overlay_key else None,
                 parts=f"{base}/parts.png" if job.parts_key else None)


def job_out(job: Registration) -> RegistrationOut:
    progress = None
    if job.status in (JobStatus.running.value, JobStatus.queued.value) and job.stage:
        loss = job.current_loss if job.current_loss is not None and np.isfinite(job.current_loss) else None
        progress = Progress(stage=job.stage, evaluations=job.evaluations, loss=loss)
    error = None
    if job.status == JobStatus.failed.value:
        error = JobError(type=f"/problems/{job.error_type or 'internal-error'}", detail=job.error_detail or "")
    return RegistrationOut(
        id=job.id,
        status=job.status,  # type: ignore[arg-type]
        model_id=job.model_id,
        created_at=as_utc(job.created_at),
        started_at=as_utc(job.started_at) if job.started_at else None,
        finished_at=as_utc(job.finished_at) if job.finished_at else None,
        attempts=job.attempts,
        photo={"media_type": job.photo_media_type, "width": job.photo_width, "height": job.photo_height},
        progress=progress,
        result=job.result if job.status in (JobStatus.succeeded.value, JobStatus.failed.value) else None,
        error=error,
        links=links(job),
    )
