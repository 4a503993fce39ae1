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
from pathlib import Path

from .core.config import Settings

REDIS_CANDIDATES = ("/usr/bin/redis-server", "/usr/sbin/redis-server", "/usr/local/bin/redis-server")


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


def _start_redis(data_dir: Path) -> tuple[subprocess.Popen[bytes], str]:
    binary = shutil.which("redis-server") or next((p for p in REDIS_CANDIDATES if Path(p).exists()), None)
    if binary is None:
        raise SystemExit(
            "vehicle-pose-service: redis-server not found; install Debian's redis-server "
            "(scripts/setup.sh does) or set VP_BROKER_URL to a running Redis"
        )
    folder = data_dir / "redis"
    folder.mkdir(parents=True, exist_ok=True)
    port = _free_port()
    # A password of this start: another local user cannot reach the queue. It goes in on stdin
    # (redis-server's "-" config file), not in the arguments that every user's ps shows.
    password = secrets.token_urlsafe(24)
    proc = subprocess.Popen(
        [binary, "-", "--port", str(port), "--bind", "127.0.0.1", "--dir", str(folder.resolve()),
         "--appendonly", "yes", "--save", "", "--daemonize", "no", "--loglevel", "warning"],
        stdin=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
    )
    assert proc.stdin is not None
    proc.stdin.write(f"requirepass {password}\n".encode())
    proc.stdin.close()
    _wait_port(port, proc, "redis-server")
    return proc, f"redis://:{password}@127.0.0.1:{port}/0"


def _bootstrap_keys(settings: Settings, *, keep_file: bool) -> dict[str, str]:
    """Create the first admin and client when there is no client yet; returns the keys it knows.

    The keys are ``VP_BOOTSTRAP_ADMIN_KEY`` / ``VP_BOOTSTRAP_CLIENT_KEY`` when set, random
    otherwise. With ``keep_file`` (the embedded set-up) they are kept in the data folder's
    ``credentials.json`` (mode 0600) so each start can print them.
    """
    from sqlalchemy import func, select

    from .core.db import session_scope
    from .core.security import create_client
    from .models import Client

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


def _terminate(procs: list[subprocess.Popen[bytes]]) -> None:
    for p in reversed(procs):
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + 20
    for p in reversed(procs):
        try:
            p.wait(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def run(args: argparse.Namespace) -> int:
    data_dir = Path(args.data_dir).resolve()
    env = dict(os.environ, VP_DATA_DIR=str(data_dir))
    procs: list[subprocess.Popen[bytes]] = []
    stopping = False

    def stop(signum: int, _frame: object) -> None:
        nonlocal stopping
        stopping = True

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    try:
        if "VP_BROKER_URL" not in os.environ:
            redis_proc, env["VP_BROKER_URL"] = _start_redis(data_dir)
            procs.append(redis_proc)
        os.environ.update(env)  # this process migrates and bootstraps with the same settings
        from .core.config import get_settings
        from .core.migrate import upgrade

        get_settings.cache_clear()
        settings = get_settings()
        upgrade()
        keys = _bootstrap_keys(settings, keep_file=True)
        procs.append(
            subprocess.Popen(
                [sys.executable, "-m", "celery", "-A", "worker.celery_app", "--quiet", "worker", "--loglevel", args.log_level,
                 "--pool", "prefork", "--concurrency", str(args.workers), "-Q", "registrations",
                 "--hostname", f"worker-{os.getpid()}@%h", "--without-mingle", "--without-gossip"],
                env=env,
            )
        )
        procs.append(
            subprocess.Popen(
                [sys.executable, "-m", "uvicorn", "app.main:app", "--host", args.host, "--port", str(args.port),
                 "--log-level", args.log_level.lower(), "--no-access-log"],
                env=env,
            )
        )
        _wait_port(args.port, procs[-1], "the API")
        url = f"http://{args.host}:{args.port}"
        print(f"vehicle-pose service on {url}  (admin page {url}/admin, API docs {url}/docs)", flush=True)
        broker = re.sub(r"//:[^@]*@", "//:***@", env["VP_BROKER_URL"])
        print(f"data: {data_dir}  broker: {broker}  workers: {args.workers}", flush=True)
        for name, key in keys.items():
            print(f"API key ({name}): {key}", flush=True)
        print(f"keys are kept in {data_dir / 'credentials.json'}; stop with Ctrl-C", flush=True)
        while not stopping:
            dead = [p for p in procs if p.poll() is not None]
            if dead:
                print(f"vehicle-pose-service: {dead[0].args[0]} exited with {dead[0].returncode}; stopping", file=sys.stderr)
                return 1
            time.sleep(0.5)
        return 0
    finally:
        _terminate(procs)


def _use_data_dir(args: argparse.Namespace) -> None:
    """Point the settings at ``--data-dir`` (read before any setting is)."""
    os.environ["VP_DATA_DIR"] = str(Path(args.data_dir).resolve())


def create_key(args: argparse.Namespace) -> int:
    _use_data_dir(args)
    from .core.config import get_settings
    from .core.db import session_scope
    from .core.migrate import upgrade
    from .core.security import create_client

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
    from .core.config import get_settings
    from .core.migrate import upgrade

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
    k = sub.add_parser("create-key", help="add an API client and print its key")
    k.add_argument("name")
    k.add_argument("--admin", action="store_true")
    m = sub.add_parser("migrate", help="apply database migrations")
    for command in (r, k, m):
        command.add_argument("--data-dir", default=os.environ.get("VP_DATA_DIR", "data"), help="the service's data folder")
    args = p.parse_args(argv if argv is not None else (sys.argv[1:] or ["run"]))
    return {"run": run, "create-key": create_key, "migrate": migrate}[args.command or "run"](args)


if __name__ == "__main__":
    sys.exit(main())
