"""Service parts without the queue: settings, storage, sniffing, migrations, the job runner."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest
from pydantic import ValidationError
from sqlalchemy import create_engine, inspect, select

from app.uploads import sniff_image
from core import config, db
from core.config import Settings
from core.migrate import alembic_config, upgrade
from core.models import Client, JobStatus, Registration
from core.security import create_client
from core.storage import LocalStorage, ObjectMissing
from vehicle_pose.render.synth import synthesize

from conftest import view
from service_stack import encode, free_port


def test_settings_refuse_unsafe_combinations(tmp_path):
    with pytest.raises(ValidationError, match="soft"):
        Settings(data_dir=tmp_path, job_soft_time_limit_s=300, job_hard_time_limit_s=300)
    with pytest.raises(ValidationError, match="visibility"):
        Settings(data_dir=tmp_path, job_hard_time_limit_s=300, visibility_timeout_s=300)
    with pytest.raises(ValidationError, match="SQLite"):
        Settings(data_dir=tmp_path, environment="production")
    with pytest.raises(ValidationError, match="24 characters"):
        Settings(environment="production", database_url="postgresql+psycopg://u:p@db/vp", bootstrap_admin_key="short")
    s = Settings(data_dir=tmp_path)
    assert s.database_url == f"sqlite:///{tmp_path.resolve() / 'vehicle_pose.db'}"
    assert s.upload_models_dir == tmp_path.resolve() / "models"


def test_settings_read_prefixed_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("VP_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("VP_MAX_ATTEMPTS", "5")
    assert Settings().max_attempts == 5 and Settings().data_dir == tmp_path


def test_local_storage_round_trip_and_refuses_escaping_keys(tmp_path):
    store = LocalStorage(tmp_path)
    store.put("photos/abc", b"data", "image/png")
    assert store.get("photos/abc") == b"data"
    store.delete("photos/abc")
    with pytest.raises(ObjectMissing):
        store.get("photos/abc")
    for key in ("../x", "/etc/passwd", "a//b", "a/./b", ""):
        with pytest.raises(ValueError):
            store.put(key, b"", "x")
    assert not list(tmp_path.rglob(".tmp-*"))


@pytest.mark.parametrize(
    "head,media_type",
    [
        (b"\xff\xd8\xff\xe0\x00\x10JFIF", "image/jpeg"),
        (b"\x89PNG\r\n\x1a\n\x00\x00", "image/png"),
        (b"RIFF\x00\x00\x00\x00WEBPVP8 ", "image/webp"),
        (b"II*\x00\x08\x00\x00\x00", "image/tiff"),
        (b"BM\x00\x00", "image/bmp"),
        (b"RIFF\x00\x00\x00\x00WAVEfmt ", None),
        (b"GIF89a", None),
        (b"<html>", None),
        (b"", None),
    ],
)
def test_sniff_image_trusts_content_not_names(head, media_type):
    assert sniff_image(head) == media_type


def test_migrations_upgrade_and_downgrade(tmp_path):
    from alembic import command

    url = f"sqlite:///{tmp_path / 'm.db'}"
    upgrade(url)
    tables = set(inspect(create_engine(url)).get_table_names())
    assert {"clients", "registrations", "alembic_version"} <= tables
    command.downgrade(alembic_config(url), "base")
    assert set(inspect(create_engine(url)).get_table_names()) == {"alembic_version"}


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
    with db.session_scope() as s:
        job = Registration(client_id=client_id, model_id="sedan", photo_key="photos/p", photo_media_type="image/png",
                           photo_width=320, photo_height=240, options={}, **fields)
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
    from test_register import perturbed

    from vehicle_pose.geometry.camera import Camera
    from worker.jobs import run_job

    from conftest import projection_error

    client_id, store = service_db
    truth = small_photo[1]
    job_id = _job(client_id, store, small_photo[0], init_camera=perturbed(truth, 3, degrees=4.0).to_dict())
    assert run_job(job_id) == "succeeded"
    job = _record(job_id)
    assert job.status == "succeeded" and job.stage == "done" and job.attempts == 1
    assert projection_error(sedan, Camera.from_dict(job.result["camera"]), truth) < 1.0
    assert store.get(job.overlay_key)[:8] == b"\x89PNG\r\n\x1a\n"
    assert store.get(job.thumbnail_key)[:3] == b"\xff\xd8\xff"
    json.dumps(job.result)


def test_s3_storage_against_an_s3_compatible_server(tmp_path):
    """S3Storage over HTTP against moto's S3-compatible server (a real server process, not a mock client)."""
    import boto3
    from moto.server import ThreadedMotoServer

    from core.storage import make_storage

    port = free_port()
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    server.start()
    try:
        endpoint = f"http://127.0.0.1:{port}"
        creds = {"aws_access_key_id": "test", "aws_secret_access_key": "test-secret"}
        boto3.client("s3", endpoint_url=endpoint, region_name="us-east-1", **creds).create_bucket(Bucket="vehicle-pose")
        settings = Settings(data_dir=tmp_path, storage_url="s3://vehicle-pose/jobs", s3_endpoint_url=endpoint,
                            s3_access_key=creds["aws_access_key_id"], s3_secret_key=creds["aws_secret_access_key"])
        store = make_storage(settings)
        store.ping()
        store.put("photos/abc", b"\x89PNG data", "image/png")
        assert store.get("photos/abc") == b"\x89PNG data"
        raw = boto3.client("s3", endpoint_url=endpoint, region_name="us-east-1", **creds)
        head = raw.head_object(Bucket="vehicle-pose", Key="jobs/photos/abc")
        assert head["ContentType"] == "image/png"
        store.delete("photos/abc")
        with pytest.raises(ObjectMissing):
            store.get("photos/abc")
        with pytest.raises(ValueError):
            store.put("../escape", b"", "x")
    finally:
        server.stop()


@pytest.fixture(scope="module")
def postgres_url():
    """A throw-away PostgreSQL server (Debian's binaries) on a free port, for the module."""
    bins = sorted(Path("/usr/lib/postgresql").glob("*/bin/initdb"))
    if not bins:
        pytest.fail("PostgreSQL is not installed; scripts/setup.sh installs Debian's postgresql")
    bindir = bins[-1].parent
    root = Path(tempfile.mkdtemp(prefix="vp-pg-"))
    as_user: list[str] = []
    if os.geteuid() == 0:  # PostgreSQL refuses to run as root
        shutil.chown(root, "postgres")
        as_user = ["runuser", "-u", "postgres", "--"]
    port = free_port()
    subprocess.run([*as_user, str(bindir / "initdb"), "-D", str(root / "db"), "-A", "trust", "-U", "vp"],
                   check=True, capture_output=True)
    subprocess.run([*as_user, str(bindir / "pg_ctl"), "-D", str(root / "db"), "-l", str(root / "log"), "-w", "start",
                    "-o", f"-p {port} -k {root} -c listen_addresses=127.0.0.1"], check=True, capture_output=True)
    try:
        yield f"postgresql+psycopg://vp@127.0.0.1:{port}/postgres"
    finally:
        subprocess.run([*as_user, str(bindir / "pg_ctl"), "-D", str(root / "db"), "-m", "fast", "stop"],
                       check=False, capture_output=True)
        shutil.rmtree(root, ignore_errors=True)


def test_postgresql_migrations_jobs_and_metrics(postgres_url, monkeypatch, tmp_path):
    from alembic import command

    from app import metrics
    from core import library, storage

    monkeypatch.setenv("VP_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("VP_DATABASE_URL", postgres_url)
    caches = (config.get_settings, db.get_engine, db.session_factory, storage.get_storage, library.get_library)
    for cache in caches:
        cache.cache_clear()
    try:
        upgrade()
        assert {"clients", "registrations"} <= set(inspect(db.get_engine()).get_table_names())
        with db.session_scope() as s:
            create_client(s, "pg-client")
            client_id = s.scalars(select(Client.id)).one()
            job = Registration(client_id=client_id, model_id="sedan", photo_key="photos/p",
                               photo_media_type="image/png",
                               photo_width=640, photo_height=480, options={"loss": "invariant"},
                               init_camera={"K": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}, bbox=[1.0, 2.0, 3.0, 4.0])
            s.add(job)
            s.flush()
            job.finish(JobStatus.failed, "invalid-pose", "off-screen")
        families = {f.name: f for f in metrics.JobCollector().collect()}
        assert {s.labels["status"]: s.value for s in families["vehicle_pose_jobs"].samples}["failed"] == 1
        count = [s for s in families["vehicle_pose_job_duration_seconds"].samples
                 if s.name.endswith("_count") and s.labels["status"] == "failed"]
        assert count[0].value == 1
        with db.session_scope() as s:
            stored = s.scalars(select(Registration)).one()
            assert stored.options == {"loss": "invariant"} and stored.bbox == [1.0, 2.0, 3.0, 4.0]
            assert stored.created_at.tzinfo is not None and stored.duration_s >= 0
        db.get_engine().dispose()
        command.downgrade(alembic_config(postgres_url), "base")
        engine = create_engine(postgres_url)
        assert "registrations" not in inspect(engine).get_table_names()
        engine.dispose()
    finally:
        db.get_engine().dispose()
        for cache in caches:
            cache.cache_clear()


def test_real_photo_options_reach_the_engine_and_are_bounded():

    from app.schemas import RegistrationOptionsIn
    from vehicle_pose import RegistrationOptions

    kwargs = RegistrationOptionsIn.model_validate_json(
        '{"edge_weight": 0, "box_weight": 2.5, "fit_start_to_box": false}').engine_kwargs()
    assert kwargs == {"edge_weight": 0.0, "box_weight": 2.5, "fit_start_to_box": False}
    terms = RegistrationOptions.from_flat(kwargs).terms
    assert (terms.edge_weight, terms.box_weight, terms.fit_start_to_box) == (0.0, 2.5, False)
    for bad in ('{"edge_weight": -1}', '{"box_weight": 1e9}', '{"fit_start_to_box": "maybe"}'):
        with pytest.raises(ValueError):
            RegistrationOptionsIn.model_validate_json(bad)


def test_create_key_needs_the_service_database(tmp_path):
    service = Path(__file__).resolve().parents[1] / ".venv" / "bin" / "vehicle-pose-service"
    env = {k: v for k, v in os.environ.items() if not k.startswith("VP_")}
    empty = tmp_path / "empty"
    refused = subprocess.run([str(service), "create-key", "someone", "--data-dir", str(empty)], env=env,
                             capture_output=True, text=True, cwd=tmp_path)
    assert refused.returncode == 2 and "no service database" in refused.stderr and not refused.stdout
    assert not (tmp_path / "data").exists() and not (empty / "vehicle_pose.db").exists()
    data = tmp_path / "svc"
    subprocess.run([str(service), "migrate", "--data-dir", str(data)], env=env, check=True, capture_output=True)
    made = subprocess.run([str(service), "create-key", "someone", "--data-dir", str(data)], env=env,
                          capture_output=True, text=True, check=True)
    assert made.stdout.strip().startswith("vp_")


@pytest.mark.parametrize(
    ("options", "words"),
    [
        ('{"max_evaluations": 1}', ("max_evaluations", "greater than")),
        ('{"loss": "nope"}', ("loss", "nope")),
        ('{"edge_weight": "heavy"}', ("edge_weight", "number")),
        ('{"max_evaluations": 1, "starts": 0}', ("max_evaluations", "starts")),
    ],
)
def test_invalid_options_name_the_field_and_the_reason(options, words):
    from app.problems import Problem
    from app.registrations import Photo, parse_hints

    photo = Photo(b"", "image/png", 640, 480)
    with pytest.raises(Problem) as info:
        parse_hints(None, None, options, photo)
    assert info.value.slug == "invalid-options"
    detail = info.value.detail
    assert "validation error for" not in detail
    for word in words:
        assert word in detail, detail


def test_a_start_camera_of_another_aspect_ratio_is_a_422():
    from app.problems import Problem
    from app.registrations import Photo, parse_hints

    cam = {"K": [[500, 0, 319.5], [0, 500, 239.5], [0, 0, 1]], "R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
           "t": [0, 0, 10], "width": 640, "height": 480}
    assert parse_hints(json.dumps(cam), None, None, Photo(b"", "image/png", 320, 240))[0]["width"] == 640
    with pytest.raises(Problem) as info:
        parse_hints(json.dumps(cam), None, None, Photo(b"", "image/png", 480, 640))
    assert info.value.slug == "invalid-camera" and "aspect ratio" in info.value.detail
