"""One registration job, from its database record to a stored result; no Celery in here.

The Celery task (``worker.tasks``) only calls :func:`run_job` and turns :class:`Retry` into a
Celery retry. Every outcome is written to the job's record: ``succeeded`` with the result, or
``failed`` with a stable error type and a reason. Nothing is left ``running`` except while a
process is really working on it.
"""

from __future__ import annotations

import logging
import os
import socket
import time

import cv2
import numpy as np
import numpy.typing as npt
from sqlalchemy.exc import OperationalError

from core.config import Settings, get_settings
from core.db import session_scope
from core.library import get_library
from core.models import JobStatus, Registration, utcnow
from core.storage import ObjectMissing, Storage, StorageUnavailable, get_storage
from vehicle_pose import (
    Camera,
    ModelLibrary,
    RegistrationOptions,
    VehiclePoseError,
    decode_photo,
)
from vehicle_pose.errors import RenderError
from vehicle_pose.photo import resized
from vehicle_pose.registration.identify import register_or_identify
from vehicle_pose.render.overlay import draw_overlay, encode_image

log = logging.getLogger(__name__)

THUMBNAIL_WIDTH = 320
OVERLAY_MAX_SIZE = 2048
"""The overlay's longer side, at most (pixels): drawn at a 24-megapixel photo's own size, the
render behind it alone holds 16 bytes a pixel (384 MB)."""


class Retry(Exception):
    """The job met a transient failure and should run again (a bounded number of times)."""


def thumbnail(rgb: npt.NDArray[np.uint8], width: int = THUMBNAIL_WIDTH) -> bytes:
    """A JPEG of ``rgb`` at most ``width`` pixels wide."""
    h, w = rgb.shape[:2]
    if w > width:
        rgb = resized(rgb, width, max(1, round(h * width / w)))
    return encode_image(rgb, ".jpg", [cv2.IMWRITE_JPEG_QUALITY, 85])


def overlay_base(rgb: npt.NDArray[np.uint8], max_size: int = OVERLAY_MAX_SIZE) -> npt.NDArray[np.uint8]:
    """The photo the overlay is drawn on: ``rgb`` reduced to at most ``max_size`` on its longer side."""
    h, w = rgb.shape[:2]
    s = max_size / max(h, w)
    if s >= 1.0:
        return rgb
    return resized(rgb, max(1, round(w * s)), max(1, round(h * s)))


def fail_job(job_id: str, error_type: str, detail: str) -> None:
    """Record that a job ended in failure (unless it already ended)."""
    with session_scope() as s:
        job = s.get(Registration, job_id)
        if job is not None and not job.ended:
            job.finish(JobStatus.failed, error_type, detail)


def _claim(job_id: str, settings: Settings) -> Registration | None:
    """Mark the job running for this process; None when it must not run (done, or too many tries)."""
    with session_scope() as s:
        job = s.get(Registration, job_id)
        if job is None:
            log.warning("job %s has no record; dropped", job_id)
            return None
        if job.ended:
            log.info("job %s is already %s; duplicate delivery ignored", job_id, job.status)
            return None
        if job.attempts >= settings.max_attempts:
            detail = f"the job was started {job.attempts} times and its worker never finished it"
            job.finish(JobStatus.failed, "worker-lost", detail)
            return None
        job.attempts += 1
        job.status = JobStatus.running.value
        job.started_at = utcnow()
        job.worker = f"{socket.gethostname()}:{os.getpid()}"
        job.stage = "starting"
        job.evaluations = 0
        job.current_loss = None
        s.flush()
        s.expunge(job)
        return job


class _Progress:
    """Writes (stage, evaluations, loss) to the job's record at most every ``interval`` seconds."""

    def __init__(self, job_id: str, interval: float) -> None:
        self.job_id = job_id
        self.interval = interval
        self.last = -np.inf
        self.stage = ""

    def __call__(self, stage: str, evaluations: int, loss: float) -> None:
        now = time.monotonic()
        if stage == self.stage and now - self.last < self.interval:
            return
        self.stage, self.last = stage, now
        with session_scope() as s:
            job = s.get(Registration, self.job_id)
            if job is not None:
                job.stage = stage
                job.evaluations = int(evaluations)
                job.current_loss = float(loss) if np.isfinite(loss) else None


def _register(job: Registration, storage: Storage, library: ModelLibrary, settings: Settings) -> None:
    options = RegistrationOptions.from_flat(job.options)
    # A large JPEG is decoded reduced, to twice the working size at least; the registration
    # still answers in the photo's own pixels.
    photo = decode_photo(storage.get(job.photo_key), max_pixels=settings.max_photo_pixels,
                         reduce_to=2 * options.pyramid.max_size)
    models = [library.load(model_id) for model_id in library.resolve(job.model_id)]
    init = Camera.from_dict(job.init_camera) if job.init_camera else None
    progress = _Progress(job.id, settings.progress_interval_s)
    result, data = register_or_identify(photo, models, init_camera=init, bbox=job.bbox, options=options,
                                        progress=progress, photo_size=(job.photo_width, job.photo_height))
    model = result.model
    base = overlay_base(photo)
    del photo  # a large photo's array need not outlive the registration
    overlay = draw_overlay(base, model.mesh, result.camera, wheels=model.wheels)
    overlay_key, thumb_key = f"overlays/{job.id}.png", f"thumbnails/{job.id}.jpg"
    storage.put(overlay_key, encode_image(overlay, ".png"), "image/png")
    storage.put(thumb_key, thumbnail(overlay), "image/jpeg")
    with session_scope() as s:
        record = s.get(Registration, job.id)
        if record is None:
            return
        record.result = data
        record.loss = float(result.loss)
        record.seconds = float(result.seconds)
        record.evaluations = int(result.evaluations)
        record.current_loss = float(result.loss)
        record.stage = "done"
        record.overlay_key = overlay_key
        record.thumbnail_key = thumb_key
        if result.failed:
            # The pose is kept for inspection, but the job does not claim success.
            record.finish(JobStatus.failed, "no-credible-pose",
                          f"no start pose led to a credible registration (confidence {result.confidence:.2f})")
        else:
            record.finish(JobStatus.succeeded)


def run_job(
    job_id: str,
    *,
    settings: Settings | None = None,
    storage: Storage | None = None,
    timeouts: tuple[type[BaseException], ...] = (),
) -> str:
    """Run one job to its end and return its final status, ``"skipped"`` when it must not run.

    Bad input found late (a pose off-screen, a broken model) fails the job with the engine's
    error type; a transient error (database, storage, OpenGL) raises :class:`Retry` until
    ``settings.max_attempts`` runs were made; ``timeouts`` are the exceptions that mean the
    soft time limit passed.
    """
    settings = settings or get_settings()
    storage = storage or get_storage()
    try:
        job = _claim(job_id, settings)
    except OperationalError as exc:
        raise Retry(f"database unavailable: {exc}") from exc
    if job is None:
        return "skipped"
    try:
        _register(job, storage, get_library(), settings)
        return JobStatus.succeeded.value
    except timeouts:
        fail_job(job_id, "timeout", f"the registration ran past {settings.job_soft_time_limit_s} s")
    except ObjectMissing:
        fail_job(job_id, "photo-missing", "the job's photo is no longer in storage")
    except RenderError as exc:
        if job.attempts < settings.max_attempts:
            raise Retry(str(exc)) from exc
        fail_job(job_id, exc.code, str(exc))
    except VehiclePoseError as exc:
        fail_job(job_id, exc.code, str(exc))
    except (OperationalError, OSError, ConnectionError) as exc:
        log.warning("job %s attempt %d: transient error: %s", job_id, job.attempts, exc)
        if job.attempts < settings.max_attempts:
            raise Retry(str(exc)) from exc
        kind = ("storage-unavailable" if isinstance(exc, StorageUnavailable)
                else "database-unavailable" if isinstance(exc, OperationalError) else "internal-error")
        fail_job(job_id, kind, f"gave up after {job.attempts} attempts: {exc}")
    except Exception as exc:
        log.exception("job %s attempt %d failed", job_id, job.attempts)
        fail_job(job_id, "internal-error", f"{type(exc).__name__}: {exc}")
    return JobStatus.failed.value


def requeue(job_id: str) -> None:
    """Put a job that will be retried back to ``queued`` so its status says so."""
    with session_scope() as s:
        job = s.get(Registration, job_id)
        if job is not None and job.status == JobStatus.running.value:
            job.status = JobStatus.queued.value
            job.stage = "retrying"
