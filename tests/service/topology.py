"""The scaled-out topology of docker-compose.yml on this machine, for the fault suite:
PostgreSQL (Debian's binaries), Redis (append-only), an S3-compatible store (moto's server),
two Celery worker processes and the API, each a real process that a test can stop, kill and
start again."""

from __future__ import annotations

import os
import secrets
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx

from service_stack import children, free_port

SERVICE_ROOT = Path(__file__).resolve().parents[2]


def _wait_port(port: int, timeout: float = 30.0) -> None:
    import socket

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                return
        except OSError:
            time.sleep(0.1)
    raise RuntimeError(f"nothing listens on port {port} after {timeout} s")


class Topology:
    """Every part of the scaled-out service, started under ``root``."""

    def __init__(self, root: Path, *, workers: int = 2) -> None:
        self.root = root
        self.n_workers = workers
        self.log = root / "topology.log"
        self.keys = {"admin": "vp_admin_" + secrets.token_urlsafe(24),
                     "default": "vp_client_" + secrets.token_urlsafe(24)}
        self.workers: list[subprocess.Popen[bytes]] = []
        self.api: subprocess.Popen[bytes] | None = None
        self.redis: subprocess.Popen[bytes] | None = None
        self.s3 = None
        self.pg_bin: Path | None = None
        self.as_user: list[str] = []

    # -- PostgreSQL ---------------------------------------------------------------------------
    def start_postgres(self) -> None:
        bins = sorted(Path("/usr/lib/postgresql").glob("*/bin/initdb"))
        if not bins:
            raise RuntimeError("PostgreSQL is not installed; scripts/setup.sh installs Debian's postgresql")
        self.pg_bin = bins[-1].parent
        # Outside the test's folder: PostgreSQL runs as its own user, who cannot enter pytest's.
        self.pg_root = Path(tempfile.mkdtemp(prefix="vp-pg-"))
        if os.geteuid() == 0:  # PostgreSQL refuses to run as root
            shutil.chown(self.pg_root, "postgres")
            self.as_user = ["runuser", "-u", "postgres", "--"]
        self.pg_port = free_port()
        subprocess.run([*self.as_user, str(self.pg_bin / "initdb"), "-D", str(self.pg_root / "db"), "-A", "trust",
                        "-U", "vp"],
                       check=True, capture_output=True)
        self._pg("start")

    def _pg(self, action: str, *extra: str) -> None:
        assert self.pg_bin is not None
        subprocess.run([*self.as_user, str(self.pg_bin / "pg_ctl"), "-D", str(self.pg_root / "db"), "-l",
                        str(self.pg_root / "log"), "-w", *extra, action,
                        "-o", f"-p {self.pg_port} -k {self.pg_root} -c listen_addresses=127.0.0.1"],
                       check=True, capture_output=True)

    def restart_postgres(self) -> None:
        self._pg("restart", "-m", "fast")

    # -- Redis --------------------------------------------------------------------------------
    def start_redis(self) -> None:
        if not hasattr(self, "redis_port"):
            self.redis_port = free_port()
            (self.root / "redis").mkdir()
        self.redis = subprocess.Popen(
            ["redis-server", "--port", str(self.redis_port), "--bind", "127.0.0.1", "--dir", str(self.root / "redis"),
             "--appendonly", "yes", "--save", "", "--loglevel", "warning"],
            stdout=subprocess.DEVNULL,
        )
        _wait_port(self.redis_port)

    def restart_redis(self) -> None:
        assert self.redis is not None
        self.redis.send_signal(signal.SIGTERM)  # writes its append-only file and exits
        self.redis.wait(timeout=20)
        self.start_redis()

    # -- S3 -----------------------------------------------------------------------------------
    def start_s3(self) -> None:
        from moto.server import ThreadedMotoServer

        if not hasattr(self, "s3_port"):
            self.s3_port = free_port()
        self.s3 = ThreadedMotoServer(ip_address="127.0.0.1", port=self.s3_port, verbose=False)
        self.s3.start()

    def s3_outage(self, seconds: float) -> None:
        """The store stops answering for ``seconds`` (its objects are kept)."""
        assert self.s3 is not None
        self.s3.stop()
        time.sleep(seconds)
        self.start_s3()

    # -- the service --------------------------------------------------------------------------
    @property
    def env(self) -> dict[str, str]:
        env = {k: v for k, v in os.environ.items() if not k.startswith("VP_")}
        cache = os.environ.get("VEHICLE_POSE_CACHE_DIR")
        env.update(
            VP_DATA_DIR=str(self.root / "data"),
            VP_DATABASE_URL=f"postgresql+psycopg://vp@127.0.0.1:{self.pg_port}/postgres",
            VP_BROKER_URL=f"redis://127.0.0.1:{self.redis_port}/0",
            VP_STORAGE_URL="s3://vehicle-pose/jobs",
            VP_S3_ENDPOINT_URL=f"http://127.0.0.1:{self.s3_port}",
            VP_S3_ACCESS_KEY="test",
            VP_S3_SECRET_KEY="test-secret",
            VP_BOOTSTRAP_ADMIN_KEY=self.keys["admin"],
            VP_BOOTSTRAP_CLIENT_KEY=self.keys["default"],
            VP_JOB_SOFT_TIME_LIMIT_S="60",
            VP_JOB_HARD_TIME_LIMIT_S="90",
            VP_VISIBILITY_TIMEOUT_S="120",
            VP_LEASE_S="8",
            VP_HEARTBEAT_INTERVAL_S="1",
            VP_PROGRESS_INTERVAL_S="0.5",
        )
        if cache:
            env["VP_PREPARED_DIR"] = str(Path(cache) / "service")
        return env

    def start(self) -> None:
        """Everything, from nothing: the stores, the bucket, the migration, workers and API."""
        import boto3

        self.start_postgres()
        self.start_redis()
        self.start_s3()
        boto3.client("s3", endpoint_url=f"http://127.0.0.1:{self.s3_port}", region_name="us-east-1",
                     aws_access_key_id="test", aws_secret_access_key="test-secret").create_bucket(Bucket="vehicle-pose")
        subprocess.run([str(SERVICE_ROOT / ".venv/bin/vehicle-pose-service"), "migrate"], env=self.env, check=True,
                       capture_output=True, cwd=self.root)
        self.start_service()

    def start_service(self) -> None:
        with self.log.open("ab") as out:  # the children keep their own copy of the descriptor
            self._start_service(out)

    def _worker(self, i: int, out: object) -> subprocess.Popen[bytes]:
        return subprocess.Popen(
            [sys.executable, "-m", "celery", "-A", "worker", "--quiet", "worker", "--loglevel", "INFO",
             "--pool", "prefork", "--concurrency", "1", "-Q", "registrations", "--hostname",
             f"w{i}-{time.time_ns()}@%h",
             "--without-mingle", "--without-gossip"],
            env=self.env, stdout=out, stderr=subprocess.STDOUT, cwd=self.root,
        )

    def replace_worker(self, i: int) -> None:
        """Worker ``i`` dies whole, its pool with it (a lost container), and a new one starts."""
        victim = self.workers[i]
        for pid in [victim.pid, *(pid for pid, _, _ in children(victim.pid))]:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        victim.wait()
        with self.log.open("ab") as out:
            self.workers[i] = self._worker(i, out)

    def _start_service(self, out: object) -> None:
        self.workers = [self._worker(i, out) for i in range(self.n_workers)]
        self.api_port = getattr(self, "api_port", None) or free_port()
        self.api = subprocess.Popen(
            [sys.executable, "-m", "uvicorn", "--factory", "app.main:create_app", "--host", "127.0.0.1", "--port",
             str(self.api_port),
             "--log-level", "warning"],
            env=self.env, stdout=out, stderr=subprocess.STDOUT, cwd=self.root,
        )
        _wait_port(self.api_port)

    def stop_service(self, drain: float = 2.0) -> None:
        """API first, then the workers: a warm stop, cut to a cold one after ``drain`` seconds."""
        for p in [self.api, *self.workers]:
            if p is not None and p.poll() is None:
                p.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + drain
        for p in self.workers:
            try:
                p.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.send_signal(signal.SIGQUIT)
        for p in [self.api, *self.workers]:
            if p is not None:
                try:
                    p.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()

    def pool_children(self) -> list[int]:
        """Pids of the workers' pool processes (the ones running jobs)."""
        return [pid for worker in self.workers for pid, _, _ in children(worker.pid)]

    def client(self) -> httpx.Client:
        return httpx.Client(base_url=f"http://127.0.0.1:{self.api_port}",
                            headers={"Authorization": f"Bearer {self.keys['default']}"}, timeout=30.0)

    def stop_all(self) -> None:
        self.stop_service(drain=0.5)
        if self.redis is not None and self.redis.poll() is None:
            self.redis.kill()
            self.redis.wait()
        if self.s3 is not None:
            self.s3.stop()
        if self.pg_bin is not None:
            try:
                self._pg("stop", "-m", "immediate")
            except subprocess.CalledProcessError:
                pass
        if hasattr(self, "pg_root"):
            shutil.rmtree(self.pg_root, ignore_errors=True)
