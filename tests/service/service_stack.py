"""The real service for tests: ``vehicle-pose-service run`` with its embedded Redis, Celery
worker processes and uvicorn, on a free port and a temporary data folder."""

from __future__ import annotations

import io
import json
import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np
from PIL import Image

from vehicle_pose.geometry.camera import Camera

SERVICE = Path(sys.executable).parent / "vehicle-pose-service"


def children(pid: int) -> list[tuple[int, str, bytes]]:
    """(pid, name, command line) of every live process whose parent is ``pid`` (read from /proc;
    a zombie, which has no command line, is left out)."""
    out = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            stat = (proc / "stat").read_text()
            cmdline = (proc / "cmdline").read_bytes()
        except OSError:
            continue
        name, rest = stat[stat.index("(") + 1 : stat.rindex(")")], stat[stat.rindex(")") + 2 :].split()
        if int(rest[1]) == pid and cmdline:
            out.append((int(proc.name), name, cmdline))
    return out


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class Stack:
    url: str
    data_dir: Path
    keys: dict[str, str]
    proc: subprocess.Popen[bytes]
    log: Path

    def client(self, key: str | None = "default") -> httpx.Client:
        headers = {"Authorization": f"Bearer {self.keys[key]}"} if key else {}
        return httpx.Client(base_url=self.url, headers=headers, timeout=30.0)

    def log_tail(self, n: int = 60) -> str:
        return "\n".join(self.log.read_text(errors="replace").splitlines()[-n:])

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=90)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def start_stack(data_dir: Path, *, workers: int = 2, extra_env: dict[str, str] | None = None,
                drain: float = 5.0) -> Stack:
    port = free_port()
    log = data_dir / "service.log"
    env = {k: v for k, v in os.environ.items() if not k.startswith("VP_")}
    if "VEHICLE_POSE_CACHE_DIR" in os.environ:  # every service of a test session prepares the models once
        env["VP_PREPARED_DIR"] = str(Path(os.environ["VEHICLE_POSE_CACHE_DIR"]) / "service")
    env.update(extra_env or {})
    with log.open("ab") as out:
        proc = subprocess.Popen(
            [str(SERVICE), "run", "--port", str(port), "--workers", str(workers), "--data-dir", str(data_dir),
             "--log-level", "INFO", "--drain-seconds", str(drain)],
            stdout=out,
            stderr=subprocess.STDOUT,
            env=env,
        )
    stack = Stack(f"http://127.0.0.1:{port}", data_dir, {}, proc, log)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"the service exited with {proc.returncode}:\n{stack.log_tail()}")
        try:
            if httpx.get(f"{stack.url}/readyz", timeout=5).status_code == 200:
                stack.keys = json.loads((data_dir / "credentials.json").read_text())
                return stack
        except httpx.HTTPError:
            pass
        time.sleep(0.5)
    stack.stop()
    raise RuntimeError(f"the service was not ready within 120 s:\n{stack.log_tail()}")


def wait_for(client: httpx.Client, job_id: str, *, timeout: float = 120.0,
             until: tuple[str, ...] = ("succeeded", "failed")) -> dict:
    """Poll a job until its status is one of ``until``; returns its last body."""
    deadline = time.monotonic() + timeout
    body: dict = {}
    while time.monotonic() < deadline:
        r = client.get(f"/v1/registrations/{job_id}")
        assert r.status_code == 200, r.text
        body = r.json()
        if body["status"] in until:
            return body
        time.sleep(0.1)
    raise AssertionError(f"job {job_id} still {body.get('status')} after {timeout} s: {body}")


def encode(rgb: np.ndarray, fmt: str = "PNG", **params) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format=fmt, **params)
    return buf.getvalue()


PROBLEM = "application/problem+json"


def submit(client, photo: bytes, *, model_id: str = "sedan", start: Camera | None = None, filename: str = "car.png",
           headers: dict | None = None, **fields):
    data = {"model_id": model_id, **fields}
    if start is not None:
        data["init_camera"] = json.dumps(start.to_dict())
    return client.post("/v1/registrations", data=data, files={"photo": (filename, photo, "image/jpeg")},
                       headers=headers)


def assert_problem(r, status: int, slug: str) -> dict:
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith(PROBLEM)
    body = r.json()
    assert body["type"] == f"/problems/{slug}" and body["status"] == status and body["detail"]
    return body


def redis_of(stack) -> tuple[int, int]:
    """Pid and port of the embedded redis-server that the stack's launcher started (its child
    named redis-server; Redis shows ``host:port`` as its process title)."""
    for pid, name, cmdline in children(stack.proc.pid):
        if name == "redis-server":
            args = cmdline.split(b"\0")
            if b"--port" in args:  # not yet retitled: its arguments
                return pid, int(args[args.index(b"--port") + 1])
            return pid, int(cmdline.decode(errors="replace").split(":")[1].split()[0].strip("\0"))
    raise AssertionError(f"no redis-server child of the launcher {stack.proc.pid}")
