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
import threading
import time
from collections.abc import Callable
from datetime import timedelta
from types import TracebackType
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
from sqlalchemy import ColumnElement, and_, func, or_, select, update
from sqlalchemy.exc import OperationalError

from core.config import Settings, get_settings
from core.db import session_scope, updated_rows
from core.library import get_library
from core.models import JobStatus, Registration, parts_key, requeued, utcnow
from core.storage import ObjectMissing, Storage, StorageUnavailable, get_storage
from vehicle_pose import (
    Camera,
    ModelLibrary,
    RegistrationOptions,
    VehiclePoseError,
    decode_photo,
)
from vehicle_pose.errors import OutOfTime, RenderError
from vehicle_pose.photo import read_focal, resized, resized_within
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
    return resized_within(rgb, max_size)


def fail_job(job_id: str, error_type: str, detail: str, result: dict[str, Any] | None = None) -> None:
    """Record that a job ended in failure (unless it already ended), with what it found."""
    with session_scope() as s:
        job = s.get(Registration, job_id)
        if job is not None and not job.ended:
            if result is not None:
                job.result = result
            job.finish(JobStatus.failed, error_type, detail)


def engine_deadline(started: float, settings: Settings) -> float:
    """When the engine must stop (``time.monotonic()``): a little before the soft time limit
    (a fifth of it, at most 5 s), so that it stops by itself and its best pose is kept; the
    soft limit's signal stays the backstop."""
    soft = float(settings.job_soft_time_limit_s)
    return started + soft - min(5.0, 0.2 * soft)


def _lease_lost(settings: Settings) -> ColumnElement[bool]:
    """Running, and its worker has not renewed the lease for ``lease_s`` (a job claimed before
    heartbeats existed counts from its start)."""
    cutoff = utcnow() - timedelta(seconds=settings.lease_s)
    return and_(Registration.status == JobStatus.running.value,
                func.coalesce(Registration.heartbeat_at, Registration.started_at) < cutoff)


def _claim(job_id: str, settings: Settings) -> Registration | None:
    """Mark the job running for this process; None when it must not run (done, too many tries, or
    running in another process whose lease holds: a second delivery of a job that is alive)."""
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
        now = utcnow()
        # One statement decides, so two deliveries of one job cannot both take it.
        taken = updated_rows(s, update(Registration)
                         .where(Registration.id == job_id, Registration.attempts == job.attempts,
                                or_(Registration.status == JobStatus.queued.value, _lease_lost(settings)))
                         .values(attempts=job.attempts + 1, status=JobStatus.running.value, started_at=now,
                                 heartbeat_at=now, worker=f"{socket.gethostname()}:{os.getpid()}",
                                 stage="starting", evaluations=0, current_loss=None))
        if not taken:
            log.info("job %s is running in %s; duplicate delivery ignored", job_id, job.worker)
            return None
        s.refresh(job)
        s.expunge(job)
        return job


class _Heartbeat:
    """Renews the job's lease (``heartbeat_at``) every ``interval`` seconds while this process
    works on it, from a thread of its own: the search holds no lock that would stop it, and a
    whole worker that dies stops renewing, so :func:`reap_stale_jobs` sends the job again."""

    def __init__(self, job: Registration, interval: float) -> None:
        self.job_id, self.worker, self.interval = job.id, job.worker, interval
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"heartbeat-{job.id}", daemon=True)

    def _run(self) -> None:
        while not self._stop.wait(self.interval):
            try:
                with session_scope() as s:
                    updated_rows(s, update(Registration)
                             .where(Registration.id == self.job_id, Registration.worker == self.worker,
                                    Registration.status == JobStatus.running.value)
                             .values(heartbeat_at=utcnow()))
            except Exception as exc:  # the database may be down for a while: try again next time
                log.warning("job %s: cannot renew its lease: %s", self.job_id, exc)

    def __enter__(self) -> _Heartbeat:
        self._thread.start()
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        self._stop.set()
        self._thread.join(timeout=self.interval + 5.0)


def reap_stale_jobs(settings: Settings, send: Callable[[str], object], limit: int = 100) -> list[str]:
    """Put the running jobs whose lease ran out back to ``queued`` (stage ``retrying``) and send
    each again with ``send(job_id)``; returns their ids.

    A whole worker that dies (SIGKILL, a lost machine or container) takes its pool's heartbeats
    with it, and its job's message stays unacknowledged in the broker until the visibility
    timeout (600 s). Each worker's main process runs this every third of ``lease_s``
    (``worker.tasks``); a job is taken back by one of them only (one conditional update each).
    If the message does come back later, its delivery finds the job ended or running elsewhere
    and is ignored.
    """
    with session_scope() as s:
        stale = list(s.scalars(select(Registration.id).where(_lease_lost(settings)).limit(limit)))
    reaped = []
    for job_id in stale:
        with session_scope() as s:
            taken = updated_rows(s, requeued(Registration.id == job_id, _lease_lost(settings)))
        if taken:
            log.warning("job %s: its worker stopped renewing the lease; sent again", job_id)
            send(job_id)
            reaped.append(job_id)
    return reaped


def resend_handed_back(send: Callable[[str], object], limit: int = 1000) -> list[str]:
    """Send again, oldest first, the jobs handed back to the queue (``queued``, stage
    ``retrying``: cut off by a stop, a lost worker, a restart), marking each ``sent again`` in
    one conditional update, so that of several workers starting together one sends it; returns
    their ids.

    A job handed back has a message in the broker only if the broker kept it: an unacknowledged
    message comes back only after the visibility timeout (600 s), and a Redis killed and
    restarted loses its last second. Each worker's main process runs this as it starts
    (``worker.tasks``). A message that does come back later finds the job ended or running and
    is ignored."""
    with session_scope() as s:
        back = list(s.scalars(select(Registration.id)
                              .where(Registration.status == JobStatus.queued.value, Registration.stage == "retrying")
                              .order_by(Registration.created_at).limit(limit)))
    sent = []
    for job_id in back:
        with session_scope() as s:
            taken = updated_rows(s, update(Registration)
                                 .where(Registration.id == job_id, Registration.status == JobStatus.queued.value,
                                        Registration.stage == "retrying")
                                 .values(stage="sent again"))
        if taken:
            send(job_id)
            sent.append(job_id)
    if sent:
        log.warning("%d job(s) handed back to the queue sent again: %s", len(sent), ", ".join(sent))
    return sent


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


def _register(job: Registration, storage: Storage, library: ModelLibrary, settings: Settings,
              deadline: float | None = None) -> None:
    options = RegistrationOptions.from_flat(job.options)
    # A large JPEG is decoded reduced, to twice the working size at least; the registration
    # still answers in the photo's own pixels.
    raw = storage.get(job.photo_key)
    photo = decode_photo(raw, max_pixels=settings.max_photo_pixels, reduce_to=2 * options.pyramid.max_size)
    exif = read_focal(raw, max_pixels=settings.max_photo_pixels)
    del raw
    models = [library.load(model_id) for model_id in library.resolve(job.model_id)]
    init = Camera.from_dict(job.init_camera) if job.init_camera else None
    progress = _Progress(job.id, settings.progress_interval_s)
    result, data = register_or_identify(photo, models, init_camera=init, bbox=job.bbox, options=options,
                                        progress=progress, photo_size=(job.photo_width, job.photo_height),
                                        exif=exif, deadline=deadline)
    model = result.model
    base = overlay_base(photo)
    del photo  # a large photo's array need not outlive the registration
    overlay = draw_overlay(base, model.mesh, result.camera, wheels=model.wheels, parts=result.parts)
    overlay_key, thumb_key = f"overlays/{job.id}.png", f"thumbnails/{job.id}.jpg"
    storage.put(overlay_key, encode_image(overlay, ".png"), "image/png")
    if result.parts is not None:
        storage.put(parts_key(job.id), result.parts.png(), "image/png")
    storage.put(thumb_key, thumbnail(overlay), "image/jpeg")
    with session_scope() as s:
        record = s.get(Registration, job.id)
        if record is None or record.ended:
            # Taken back and finished by another process while this one was late: the first
            # result stands.
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
    started = time.monotonic()
    settings = settings or get_settings()
    storage = storage or get_storage()
    try:
        job = _claim(job_id, settings)
    except OperationalError as exc:
        raise Retry(f"database unavailable: {exc}") from exc
    if job is None:
        return "skipped"
    try:
        with _Heartbeat(job, settings.heartbeat_interval_s):
            _register(job, storage, get_library(), settings, engine_deadline(started, settings))
        return JobStatus.succeeded.value
    except OutOfTime as exc:
        # The engine stopped at its deadline: the best pose of the stages it finished is kept.
        kept = None if exc.camera is None else {"camera": exc.camera.to_dict(), "pose_stage": exc.stage,
                                                 "best_so_far": True}
        fail_job(job_id, "timeout", f"the registration ran past its time limit of {settings.job_soft_time_limit_s} s"
                 + ("; the best pose found by then is in result" if kept else ""), kept)
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
        updated_rows(s, requeued(Registration.id == job_id))
