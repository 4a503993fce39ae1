"""The job runner: failed, duplicate and late-bad jobs, results, overlays and thumbnails, leases."""

from __future__ import annotations

import json
import time
from datetime import timedelta

import pytest
from sqlalchemy import select

from core import config, db
from core.migrate import upgrade
from core.models import Client, JobStatus, Registration, utcnow
from core.security import create_client
from vehicle_pose.render.synth import synthesize

from helpers import view
from service_stack import encode


@pytest.fixture
def service_db(tmp_path, monkeypatch):
    """Settings, database and storage of a service in ``tmp_path`` (no broker needed)."""
    from core import library, storage

    monkeypatch.setenv("VP_DATA_DIR", str(tmp_path))
    caches = (config.get_settings, db.get_engine, db.session_factory, storage.get_storage, library.get_library)
    for cache in caches:
        cache.cache_clear()
    upgrade()
    with db.session_scope() as s:
        create_client(s, "tester")
        client_id = s.scalars(select(Client.id)).one()
    yield client_id, storage.get_storage()
    db.get_engine().dispose()
    for cache in caches:
        cache.cache_clear()


def _job(client_id: str, store, photo: bytes, **fields) -> str:
    from vehicle_pose.photo import verify_photo

    width, height = verify_photo(photo)
    with db.session_scope() as s:
        job = Registration(client_id=client_id, model_id="sedan", photo_key="photos/p", photo_media_type="image/png",
                           photo_width=width, photo_height=height, options={}, **fields)
        s.add(job)
        s.flush()
        job_id = job.id
    store.put("photos/p", photo, "image/png")
    return job_id


def _record(job_id: str) -> Registration:
    with db.session_scope() as s:
        job = s.get(Registration, job_id)
        s.expunge(job)
        return job


@pytest.fixture(scope="module")
def small_photo(sedan, renderer):
    truth = view(sedan, 60.0, 15.0, width=320, height=240, focal=450.0)
    photo, _ = synthesize(sedan.mesh, truth, renderer=renderer)
    return encode(photo), truth


def test_run_job_fails_a_job_whose_worker_kept_dying(service_db, small_photo):
    from worker.jobs import run_job

    client_id, store = service_db
    job_id = _job(client_id, store, small_photo[0], attempts=3, status=JobStatus.running.value)
    assert run_job(job_id) == "skipped"
    job = _record(job_id)
    assert job.status == "failed" and job.error_type == "worker-lost" and job.duration_s is not None


def test_run_job_ignores_a_duplicate_delivery_of_a_finished_job(service_db, small_photo):
    from worker.jobs import run_job

    client_id, store = service_db
    job_id = _job(client_id, store, small_photo[0], status=JobStatus.succeeded.value, attempts=1)
    assert run_job(job_id) == "skipped"
    assert _record(job_id).attempts == 1


def test_a_job_running_in_a_live_process_is_not_taken_twice(service_db, small_photo):
    from worker.jobs import run_job

    client_id, store = service_db
    alive = _job(client_id, store, small_photo[0], status=JobStatus.running.value, attempts=1, worker="other:1",
                 started_at=utcnow(), heartbeat_at=utcnow())
    assert run_job(alive) == "skipped"
    job = _record(alive)
    assert (job.status, job.attempts, job.worker) == ("running", 1, "other:1")
    # The same job once its lease (30 s) ran out: its worker is gone, this delivery takes it.
    lost = _job(client_id, store, small_photo[0], status=JobStatus.running.value, attempts=1, worker="other:1",
                started_at=utcnow() - timedelta(seconds=120), heartbeat_at=utcnow() - timedelta(seconds=31))
    assert run_job(lost) == "succeeded"
    job = _record(lost)
    assert job.status == "succeeded" and job.attempts == 2 and job.worker != "other:1"


def test_reap_stale_jobs_sends_back_only_the_jobs_whose_lease_ran_out(service_db, small_photo):
    from worker.jobs import reap_stale_jobs

    client_id, store = service_db
    now = utcnow()
    stale = _job(client_id, store, small_photo[0], status=JobStatus.running.value, attempts=1,
                 started_at=now - timedelta(seconds=90), heartbeat_at=now - timedelta(seconds=45))
    legacy = _job(client_id, store, small_photo[0], status=JobStatus.running.value, attempts=1,
                  started_at=now - timedelta(seconds=90))
    fresh = _job(client_id, store, small_photo[0], status=JobStatus.running.value, attempts=1,
                 started_at=now - timedelta(seconds=90), heartbeat_at=now - timedelta(seconds=5))
    waiting = _job(client_id, store, small_photo[0])
    sent: list[str] = []
    assert sorted(reap_stale_jobs(config.get_settings(), sent.append)) == sorted([stale, legacy]) == sorted(sent)
    for job_id in (stale, legacy):
        job = _record(job_id)
        assert (job.status, job.stage, job.attempts) == ("queued", "retrying", 1)
    assert _record(fresh).status == "running" and _record(waiting).status == "queued"
    assert reap_stale_jobs(config.get_settings(), sent.append) == [] and len(sent) == 2


def test_jobs_handed_back_are_sent_again_once_oldest_first(service_db, small_photo):
    from worker.jobs import resend_handed_back

    client_id, store = service_db
    first = _job(client_id, store, small_photo[0], stage="retrying", attempts=1)
    second = _job(client_id, store, small_photo[0], stage="retrying", attempts=1)
    waiting = _job(client_id, store, small_photo[0])
    running = _job(client_id, store, small_photo[0], status=JobStatus.running.value, stage="retrying", attempts=1)
    sent: list[str] = []
    assert resend_handed_back(sent.append) == sent == [first, second]
    assert all(_record(j).stage == "sent again" and _record(j).status == "queued" for j in (first, second))
    assert _record(waiting).stage != "sent again" and _record(running).status == "running"
    assert resend_handed_back(sent.append) == [] and len(sent) == 2  # another worker starting sends nothing


def test_the_heartbeat_renews_the_lease_while_the_job_runs(service_db, small_photo):
    from worker.jobs import _Heartbeat

    client_id, store = service_db
    start = utcnow() - timedelta(seconds=20)
    job_id = _job(client_id, store, small_photo[0], status=JobStatus.running.value, attempts=1, worker="me:1",
                  started_at=start, heartbeat_at=start)
    with _Heartbeat(_record(job_id), 0.05):
        time.sleep(0.4)
    renewed = _record(job_id).heartbeat_at
    assert renewed is not None and renewed.replace(tzinfo=None) > start.replace(tzinfo=None) + timedelta(seconds=19)
    # Another process's job is left alone.
    other = _job(client_id, store, small_photo[0], status=JobStatus.running.value, attempts=1, worker="you:2",
                 started_at=start, heartbeat_at=start)
    record = _record(other)
    record.worker = "me:1"
    with _Heartbeat(record, 0.05):
        time.sleep(0.3)
    assert _record(other).heartbeat_at.replace(tzinfo=None) == start.replace(tzinfo=None)


def test_run_job_reports_bad_input_found_late(service_db, small_photo):
    from worker.jobs import run_job

    client_id, store = service_db
    truth = small_photo[1]
    behind = truth.to_dict() | {"t": [0.0, 0.0, -8.0]}
    job_id = _job(client_id, store, small_photo[0], init_camera=behind)
    assert run_job(job_id) == "failed"
    job = _record(job_id)
    assert job.error_type == "invalid-pose", job.error_detail
    assert job.attempts == 1

    gone = _job(client_id, store, small_photo[0])
    store.delete("photos/p")
    assert run_job(gone) == "failed"
    assert _record(gone).error_type == "photo-missing"


def test_run_job_stores_result_overlay_and_thumbnail(service_db, small_photo, sedan):
    from vehicle_pose.geometry.camera import Camera
    from worker.jobs import run_job

    from helpers import perturbed, projection_error

    client_id, store = service_db
    truth = small_photo[1]
    job_id = _job(client_id, store, small_photo[0], init_camera=perturbed(truth, 3, degrees=4.0).to_dict())
    assert run_job(job_id) == "succeeded"
    job = _record(job_id)
    assert job.status == "succeeded" and job.stage == "done" and job.attempts == 1
    assert projection_error(sedan, Camera.from_dict(job.result["camera"]), truth) < 1.0
    assert store.get(job.overlay_key)[:8] == b"\x89PNG\r\n\x1a\n"
    assert store.get(job.thumbnail_key)[:3] == b"\xff\xd8\xff"
    assert job.parts_key is not None and store.get(job.parts_key)[:8] == b"\x89PNG\r\n\x1a\n"
    assert job.result["parts"] and all(p["pixels"] > 0 for p in job.result["parts"])
    json.dumps(job.result)


@pytest.mark.parametrize("fmt", ["PNG", "JPEG"])
def test_the_overlay_of_a_large_photo_is_drawn_reduced_and_the_pose_is_the_photos(service_db, sedan, renderer, fmt):
    """A JPEG is also decoded reduced (to half its size here, twice the working size at least);
    either way the pose answers in the photo's own pixels, and so does the EXIF focal length."""
    import cv2
    import numpy as np
    from PIL import ExifTags, Image

    from vehicle_pose.geometry.camera import Camera
    from worker.jobs import OVERLAY_MAX_SIZE, run_job

    from helpers import perturbed, projection_error

    client_id, store = service_db
    truth = view(sedan, 60.0, 15.0, width=2880, height=2160, focal=4050.0)
    big, _ = synthesize(sedan.mesh, truth, renderer=renderer)
    exif = Image.Exif()
    exif.get_ifd(ExifTags.IFD.Exif)[0xA405] = 49  # 4050 pixels of a 3600-pixel diagonal, 35 mm equivalent
    data = encode(big, fmt, quality=92, exif=exif) if fmt == "JPEG" else encode(big)
    job_id = _job(client_id, store, data, init_camera=perturbed(truth, 3, degrees=4.0).to_dict())
    assert run_job(job_id) == "succeeded"
    job = _record(job_id)
    found = Camera.from_dict(job.result["camera"])
    assert (found.width, found.height) == (2880, 2160)
    assert projection_error(sedan, found.scaled(640, 480), truth.scaled(640, 480)) < 1.5
    overlay = cv2.imdecode(np.frombuffer(store.get(job.overlay_key), np.uint8), cv2.IMREAD_COLOR)
    assert overlay.shape[:2] == (round(2160 * OVERLAY_MAX_SIZE / 2880), OVERLAY_MAX_SIZE)
    # The client's start camera wins over the EXIF, which the result still reports.
    assert job.result["focal"]["source"] == "searched"
    if fmt == "JPEG":
        assert job.result["focal"]["exif"]["pixels"] == pytest.approx(4050.0, rel=0.01)
    else:
        assert job.result["focal"]["exif"] is None

