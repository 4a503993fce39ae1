"""The launcher under faults, against the real parts: its Redis killed, and a stop while a job
runs (tests/service_stack.py starts `vehicle-pose-service run` with an embedded Redis)."""

from __future__ import annotations

import json
import os
import signal
import sqlite3
import time
from pathlib import Path

import httpx
from test_service_api import _redis, scene, submit  # noqa: F401 (scene is a fixture)

from service_stack import encode, start_stack, wait_for


def test_the_launcher_restarts_its_redis_and_the_service_carries_on(tmp_path, scene):  # noqa: F811
    stack = start_stack(tmp_path, workers=1)
    try:
        pid, port = _redis(stack)
        os.kill(pid, signal.SIGTERM)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            assert stack.proc.poll() is None, stack.log_tail()
            assert httpx.get(f"{stack.url}/healthz", timeout=5).status_code == 200
            try:
                again, again_port = _redis(stack)
            except AssertionError:
                time.sleep(0.2)
                continue
            if again != pid:
                break
            time.sleep(0.2)
        else:
            raise AssertionError(f"redis was not restarted:\n{stack.log_tail()}")
        assert again_port == port  # the same URL for every client
        assert "redis-server exited" in stack.log.read_text()
        with stack.client() as c:
            deadline = time.monotonic() + 60
            while True:
                r = submit(c, encode(scene[0]), start=scene[2])
                if r.status_code == 202 or time.monotonic() > deadline:
                    break
                assert r.status_code == 503, r.text  # while the workers reconnect
                time.sleep(1.0)
            assert r.status_code == 202, r.text
            assert wait_for(c, r.json()["id"], timeout=120)["status"] == "succeeded"
    finally:
        stack.stop()


def _status(data_dir: Path, job_id: str) -> tuple[str, int]:
    with sqlite3.connect(data_dir / "vehicle_pose.db") as db:
        return db.execute("SELECT status, attempts FROM registrations WHERE id = ?", (job_id,)).fetchone()


def test_a_stop_hands_running_jobs_back_and_they_run_after_the_restart(tmp_path, scene):  # noqa: F811
    stack = start_stack(tmp_path, workers=1, drain=1.0)
    try:
        with stack.client() as c:
            options = json.dumps({"max_evaluations": 2000})
            job_id = submit(c, encode(scene[0]), start=scene[2], options=options).json()["id"]
            wait_for(c, job_id, until=("running",), timeout=60)
            time.sleep(2.0)
    finally:
        t = time.monotonic()
        stack.stop()
    assert stack.proc.returncode == 0 and time.monotonic() - t < 60
    log = stack.log.read_text()
    assert "handing them back to the queue" in log
    status, attempts = _status(tmp_path, job_id)
    assert (status, attempts) == ("queued", 1), log[-3000:]
    stack = start_stack(tmp_path, workers=1)
    try:
        with stack.client() as c:
            body = wait_for(c, job_id, timeout=240)
            assert body["status"] == "succeeded" and body["attempts"] == 2, body
    finally:
        stack.stop()
