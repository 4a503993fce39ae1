"""``vehicle-pose-service``: run the whole service on one machine with embedded defaults.

``run`` starts a Redis server (Debian's ``redis-server``, on a free local port, its data under
the data folder) unless ``VP_BROKER_URL`` names one, migrates the database, creates the first
API keys, then supervises N Celery worker processes and the API (uvicorn) until interrupted.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from core.config import Settings

REDIS_CANDIDATES = ("/usr/bin/redis-server", "/usr/sbin/redis-server", "/usr/local/bin/redis-server")
RESTART_MAX_S = 30.0
"""Longest wait before a process that keeps dying is started again."""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _wait_port(port: int, proc: subprocess.Popen[bytes], what: str, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise SystemExit(f"vehicle-pose-service: {what} exited with code {proc.returncode}")
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                return
        except OSError:
            time.sleep(0.1)
    raise SystemExit(f"vehicle-pose-service: {what} did not listen on port {port} within {timeout:.0f} s")


def _start_redis(data_dir: Path, port: int | None = None,
                 password: str | None = None) -> tuple[subprocess.Popen[bytes], str]:
    """Debian's redis-server on ``port`` (a free one by default) with ``password`` (a new one
    by default); a restart passes both again, so every client's URL stays valid."""
    binary = shutil.which("redis-server") or next((p for p in REDIS_CANDIDATES if Path(p).exists()), None)
    if binary is None:
        raise SystemExit(
            "vehicle-pose-service: redis-server not found; install Debian's redis-server "
            "(scripts/setup.sh does) or set VP_BROKER_URL to a running Redis"
        )
    folder = data_dir / "redis"
    folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    folder.chmod(0o700)
    port = port or _free_port()
    # A password of this start: another local user cannot reach the queue. It goes in on stdin
    # (redis-server's "-" config file), not in the arguments that every user's ps shows.
    password = password or secrets.token_urlsafe(24)
    proc = subprocess.Popen(
        [binary, "-", "--port", str(port), "--bind", "127.0.0.1", "--dir", str(folder.resolve()),
         "--appendonly", "yes", "--save", "", "--daemonize", "no", "--loglevel", "warning"],
        stdin=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        umask=0o077,  # the append-only files hold the jobs' hints: this user's alone
    )
    assert proc.stdin is not None
    proc.stdin.write(f"requirepass {password}\n".encode())
    proc.stdin.close()
    _wait_port(port, proc, "redis-server")
    return proc, f"redis://:{password}@127.0.0.1:{port}/0"


@dataclass
class _Child:
    """One supervised process: how to start it, and its restart history."""

    name: str
    start: Callable[[], subprocess.Popen[bytes]]
    proc: subprocess.Popen[bytes] | None = None
    started: float = 0.0
    failures: int = 0
    due: float = 0.0

    def run(self) -> None:
        self.proc = self.start()
        self.started = time.monotonic()

    def check(self, now: float) -> None:
        """Restart the process when it died, after a delay that doubles with each quick death
        (0.5 s up to RESTART_MAX_S; a process that ran a minute starts the count again)."""
        if self.proc is not None and self.proc.poll() is not None:
            code = self.proc.returncode
            self.failures = 0 if now - self.started > 60.0 else self.failures + 1
            delay = min(RESTART_MAX_S, 0.5 * 2.0 ** self.failures)
            print(f"vehicle-pose-service: {self.name} exited with {code}; restarting in {delay:.1f} s",
                  file=sys.stderr, flush=True)
            self.proc, self.due = None, now + delay
        if self.proc is None and now >= self.due:
            try:
                self.run()
            except (OSError, SystemExit) as exc:
                self.failures += 1
                self.due = now + min(RESTART_MAX_S, 0.5 * 2.0 ** self.failures)
                print(f"vehicle-pose-service: cannot restart {self.name}: {exc}", file=sys.stderr, flush=True)


def _bootstrap_keys(settings: Settings, *, keep_file: bool) -> dict[str, str]:
    """Create the first admin and client when there is no client yet; returns the keys it knows.

    The keys are ``VP_BOOTSTRAP_ADMIN_KEY`` / ``VP_BOOTSTRAP_CLIENT_KEY`` when set, random
    otherwise. With ``keep_file`` (the embedded set-up) they are kept in the data folder's
    ``credentials.json`` (mode 0600) so each start can print them.
    """
    from sqlalchemy import func, select

    from core.db import session_scope
    from core.models import Client
    from core.security import create_client

    path = settings.data_dir / "credentials.json"
    with session_scope() as s:
        if (s.scalar(select(func.count()).select_from(Client)) or 0) > 0:
            return json.loads(path.read_text()) if keep_file and path.exists() else {}
        admin_key = settings.bootstrap_admin_key.get_secret_value() if settings.bootstrap_admin_key else None
        client_key = settings.bootstrap_client_key.get_secret_value() if settings.bootstrap_client_key else None
        keys = {
            "admin": create_client(s, "admin", admin=True, key=admin_key),
            "default": create_client(s, "default", key=client_key),
        }
    if keep_file:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w") as f:
            json.dump(keys, f, indent=2)
    return keys


def _stop(child: _Child | None, sig: signal.Signals, wait: float) -> None:
    p = child.proc if child is not None else None
    if p is None or p.poll() is not None:
        return
    p.send_signal(sig)
    try:
        p.wait(timeout=wait)
    except subprocess.TimeoutExpired:
        print(f"vehicle-pose-service: {child.name} still running after {wait:.0f} s; killing it",  # type: ignore[union-attr]
              file=sys.stderr, flush=True)
        p.kill()
        p.wait()


def _shutdown(api: _Child | None, workers: _Child | None, redis: _Child | None, drain: float) -> None:
    """Stop in order: the API stops accepting and finishes its requests; the workers finish
    their jobs for up to ``drain`` seconds, then stop at once (a cold shutdown hands the jobs
    still running back to the queue, and their records say ``queued``); Redis last, so that
    the workers can hand their jobs back."""
    _stop(api, signal.SIGTERM, 20.0)
    if workers is not None and workers.proc is not None and workers.proc.poll() is None:
        workers.proc.send_signal(signal.SIGTERM)  # warm shutdown: no new job, running ones finish
        try:
            workers.proc.wait(timeout=drain)
        except subprocess.TimeoutExpired:
            print(f"vehicle-pose-service: jobs still running after {drain:.0f} s; handing them back to the queue",
                  file=sys.stderr, flush=True)
            _stop(workers, signal.SIGQUIT, 30.0)
        if workers.proc.poll() is not None:
            _hand_back()
    _stop(redis, signal.SIGTERM, 20.0)


def _hand_back() -> None:
    """After this launcher's workers are gone, no job of this machine is running: a job whose
    record still says so was cut off by the stop, and its message is back in the queue
    (acks_late), so its record says ``queued`` until a worker takes it again."""
    from core.db import session_scope, updated_rows
    from core.models import Registration, requeued

    try:
        with session_scope() as s:
            done = updated_rows(s, requeued(Registration.worker.like(f"{socket.gethostname()}:%")))
        if done:
            print(f"vehicle-pose-service: {done} running job(s) handed back to the queue", file=sys.stderr, flush=True)
    except Exception as exc:  # the database may be what failed
        print(f"vehicle-pose-service: cannot mark the cut-off jobs queued: {exc}", file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:
    """Start Redis (unless ``VP_BROKER_URL`` names one), migrate, bootstrap keys, then supervise
    the workers and the API: whichever dies is restarted with backoff while the others run on
    (the API answers 503 while the broker is away). SIGTERM or Ctrl-C stops them in order."""
    data_dir = Path(args.data_dir).resolve()
    env = dict(os.environ, VP_DATA_DIR=str(data_dir))
    stopping = False

    def stop(signum: int, _frame: object) -> None:
        nonlocal stopping
        stopping = True

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    redis: _Child | None = None
    workers: _Child | None = None
    api: _Child | None = None
    try:
        if "VP_BROKER_URL" not in os.environ:
            proc, url = _start_redis(data_dir)
            env["VP_BROKER_URL"] = url
            port = int(url.rsplit(":", 1)[1].split("/")[0])
            password = url.split("//:", 1)[1].split("@", 1)[0]
            redis = _Child("redis-server", lambda: _start_redis(data_dir, port, password)[0], proc, time.monotonic())
        os.environ.update(env)  # this process migrates and bootstraps with the same settings
        from core.config import get_settings
        from core.migrate import upgrade

        get_settings.cache_clear()
        settings = get_settings()
        upgrade()
        keys = _bootstrap_keys(settings, keep_file=True)
        workers = _Child("the workers", lambda: subprocess.Popen(
            [sys.executable, "-m", "celery", "-A", "worker", "--quiet", "worker", "--loglevel", args.log_level,
             "--pool", "prefork", "--concurrency", str(args.workers), "-Q", "registrations",
             "--hostname", f"worker-{os.getpid()}@%h", "--without-mingle", "--without-gossip"],
            env=env,
        ))
        api = _Child("the API", lambda: subprocess.Popen(
            [sys.executable, "-m", "uvicorn", "--factory", "app.main:create_app", "--host", args.host, "--port",
             str(args.port),
             "--log-level", args.log_level.lower(), "--no-access-log"],
            env=env,
        ))
        workers.run()
        api.run()
        assert api.proc is not None
        _wait_port(args.port, api.proc, "the API")
        url = f"http://{args.host}:{args.port}"
        print(f"vehicle-pose service on {url}  (admin page {url}/admin, API docs {url}/docs)", flush=True)
        broker = re.sub(r"//:[^@]*@", "//:***@", env["VP_BROKER_URL"])
        print(f"data: {data_dir}  broker: {broker}  workers: {args.workers}", flush=True)
        for name, key in keys.items():
            print(f"API key ({name}): {key}", flush=True)
        print(f"keys are kept in {data_dir / 'credentials.json'}; stop with Ctrl-C", flush=True)
        while not stopping:
            now = time.monotonic()
            for child in (redis, workers, api):
                if child is not None:
                    child.check(now)
            time.sleep(0.25)
        return 0
    finally:
        _shutdown(api, workers, redis, args.drain_seconds)


def _use_data_dir(args: argparse.Namespace) -> None:
    """Point the settings at ``--data-dir`` (read before any setting is)."""
    os.environ["VP_DATA_DIR"] = str(Path(args.data_dir).resolve())


def create_key(args: argparse.Namespace) -> int:
    _use_data_dir(args)
    from core.config import get_settings
    from core.db import session_scope
    from core.migrate import upgrade
    from core.security import create_client

    settings = get_settings()
    db_file = settings.data_dir / "vehicle_pose.db"
    if settings.database_url.startswith("sqlite") and not db_file.is_file():
        # A key in a database no service uses works nowhere: say so instead of making one.
        print(f"vehicle-pose-service: error: no service database at {db_file}; give the service's "
              f"--data-dir (or VP_DATA_DIR), or run the service there once", file=sys.stderr)
        return 2
    upgrade()
    with session_scope() as s:
        key = create_client(s, args.name, admin=args.admin)
    print(key)
    return 0


def migrate(args: argparse.Namespace) -> int:
    """Apply migrations; on a database with no client yet, create the bootstrap admin and client."""
    _use_data_dir(args)
    from core.config import get_settings
    from core.migrate import upgrade

    upgrade()
    settings = get_settings()
    if settings.bootstrap_admin_key is not None:
        created = _bootstrap_keys(settings, keep_file=False)
        if created:
            print("created the bootstrap admin and default clients")
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="vehicle-pose-service", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command")
    r = sub.add_parser("run", help="run API, workers and an embedded Redis (the default command)")
    r.add_argument("--host", default="127.0.0.1")
    r.add_argument("--port", type=int, default=8000)
    r.add_argument("--workers", type=int, default=2, help="worker processes, each with one EGL context")
    r.add_argument("--log-level", default="WARNING", choices=["DEBUG", "INFO", "WARNING", "ERROR"])
    r.add_argument("--drain-seconds", type=float, default=60.0,
                   help="on stop, how long running jobs may finish before they are handed back to the queue")
    k = sub.add_parser("create-key", help="add an API client and print its key")
    k.add_argument("name")
    k.add_argument("--admin", action="store_true")
    m = sub.add_parser("migrate", help="apply database migrations")
    for command in (r, k, m):
        command.add_argument("--data-dir", default=os.environ.get("VP_DATA_DIR", "data"),
                             help="the service's data folder")
    args = p.parse_args(argv if argv is not None else (sys.argv[1:] or ["run"]))
    return {"run": run, "create-key": create_key, "migrate": migrate}[args.command or "run"](args)


if __name__ == "__main__":
    sys.exit(main())
