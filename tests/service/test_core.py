"""The service core: settings, storage, migrations, S3 and PostgreSQL."""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest
from pydantic import ValidationError
from sqlalchemy import create_engine, inspect, select

from core import config, db
from core.config import Settings
from core.migrate import alembic_config, upgrade
from core.models import Client, JobStatus, Registration
from core.security import create_client
from core.storage import LocalStorage, ObjectMissing

from service_stack import free_port


def test_settings_refuse_unsafe_combinations(tmp_path):
    with pytest.raises(ValidationError, match="soft"):
        Settings(data_dir=tmp_path, job_soft_time_limit_s=300, job_hard_time_limit_s=300)
    with pytest.raises(ValidationError, match="visibility"):
        Settings(data_dir=tmp_path, job_hard_time_limit_s=300, visibility_timeout_s=300)
    with pytest.raises(ValidationError, match="lease_s"):
        Settings(data_dir=tmp_path, lease_s=8.0, heartbeat_interval_s=5.0)
    with pytest.raises(ValidationError, match="lease_s"):
        Settings(data_dir=tmp_path, lease_s=700.0)
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


def test_migrations_upgrade_and_downgrade(tmp_path):
    from alembic import command

    url = f"sqlite:///{tmp_path / 'm.db'}"
    upgrade(url)
    tables = set(inspect(create_engine(url)).get_table_names())
    assert {"clients", "registrations", "alembic_version"} <= tables
    command.downgrade(alembic_config(url), "base")
    assert set(inspect(create_engine(url)).get_table_names()) == {"alembic_version"}


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
