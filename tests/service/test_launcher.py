"""Service parts without the queue: settings, storage, sniffing, migrations, the job runner."""

from __future__ import annotations

import json
import os
import shutil
import signal
import sqlite3
import subprocess
import time
from pathlib import Path

import httpx

from service_stack import children, encode, redis_of, start_stack, submit, wait_for


def test_create_key_needs_the_service_database(tmp_path):
    service = Path(__file__).resolve().parents[2] / ".venv" / "bin" / "vehicle-pose-service"
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


def test_the_launcher_restarts_its_redis_and_the_service_carries_on(tmp_path, scene):
    stack = start_stack(tmp_path, workers=1)
    try:
        pid, port = redis_of(stack)
        os.kill(pid, signal.SIGTERM)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            assert stack.proc.poll() is None, stack.log_tail()
            assert httpx.get(f"{stack.url}/healthz", timeout=5).status_code == 200
            try:
                again, again_port = redis_of(stack)
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
        # The queue's files (the jobs' hints) are this user's alone.
        folder = tmp_path / "redis"
        assert folder.stat().st_mode & 0o077 == 0
        kept = [p for p in folder.rglob("*") if p.is_file()]
        assert kept and all(p.stat().st_mode & 0o077 == 0 for p in kept), [oct(p.stat().st_mode) for p in kept]
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


def _long_job_running(c: httpx.Client, scene, seconds: float) -> str:
    """Submit a job that runs for a while and return its id once it has run for ``seconds``.

    CMA-ES with this budget runs about 6000 evaluations, 16 s on the 2-core VM; the downhill
    simplex converges after some 1300 whatever its budget, 4 s there and 3 s on a faster machine,
    which ended one such job before the stop."""
    options = json.dumps({"max_evaluations": 5000, "optimizer": "cma-es"})
    job_id = submit(c, encode(scene[0]), start=scene[2], options=options).json()["id"]
    wait_for(c, job_id, until=("running",), timeout=60)
    time.sleep(seconds)
    return str(job_id)


def test_a_stop_hands_running_jobs_back_and_they_run_after_the_restart(tmp_path, scene):
    stack = start_stack(tmp_path, workers=1, drain=1.0)
    try:
        with stack.client() as c:
            job_id = _long_job_running(c, scene, 2.0)
    finally:
        t = time.monotonic()
        stack.stop()
    assert stack.proc.returncode == 0 and time.monotonic() - t < 60
    log = stack.log.read_text()
    assert "handing them back to the queue" in log
    status, attempts = _status(tmp_path, job_id)
    assert (status, attempts) == ("queued", 1), log[-3000:]
    # The broker loses what it held (a Redis killed loses its last second): the job handed back
    # is sent again by the next worker as it starts, not left to a message that may never come.
    shutil.rmtree(tmp_path / "redis")
    stack = start_stack(tmp_path, workers=1)
    try:
        with stack.client() as c:
            body = wait_for(c, job_id, timeout=240)
            assert body["status"] == "succeeded" and body["attempts"] == 2, body
        assert "sent again" in stack.log.read_text()
    finally:
        stack.stop()


def test_a_job_handed_back_runs_before_the_jobs_queued_after_it(tmp_path, scene):
    """One worker: a long job runs, three more wait behind it; the service stops and hands the
    long job back. After the restart it runs first, not after the jobs queued behind it."""
    stack = start_stack(tmp_path, workers=1, drain=1.0)
    try:
        with stack.client() as c:
            first = _long_job_running(c, scene, 1.0)
            quick = json.dumps({"max_evaluations": 40})
            behind = [submit(c, encode(scene[0]), start=scene[2], options=quick).json()["id"] for _ in range(3)]
    finally:
        stack.stop()
    assert _status(tmp_path, first) == ("queued", 1)
    assert all(_status(tmp_path, job_id)[0] == "queued" for job_id in behind)
    stack = start_stack(tmp_path, workers=1)
    try:
        with stack.client() as c:
            bodies = {job_id: wait_for(c, job_id, timeout=240) for job_id in [first, *behind]}
        assert all(b["status"] == "succeeded" for b in bodies.values()), bodies
        assert bodies[first]["attempts"] == 2
        started = {job_id: b["started_at"] for job_id, b in bodies.items()}
        assert started[first] < min(started[j] for j in behind), started
    finally:
        stack.stop()


def test_a_whole_worker_killed_mid_job_is_taken_back_within_its_lease(tmp_path, scene):
    """The worker's main process and its pool die together (a lost container or machine): the
    job's message stays unacknowledged until the broker's visibility timeout (600 s), but its
    lease (4 s here) runs out, a worker's reaper puts the job back and sends it again."""
    stack = start_stack(tmp_path, workers=1, extra_env={"VP_LEASE_S": "4", "VP_HEARTBEAT_INTERVAL_S": "1"})
    try:
        with stack.client() as c:
            job_id = _long_job_running(c, scene, 1.5)
            workers = [pid for pid, _, cmd in children(stack.proc.pid) if b"celery" in cmd]
            assert len(workers) == 1, children(stack.proc.pid)
            pool = [pid for pid, _, _ in children(workers[0])]
            killed = time.monotonic()
            for pid in [workers[0], *pool]:
                os.kill(pid, signal.SIGKILL)
            # The launcher starts a new worker; its reaper finds the lease run out and sends the
            # job again. (The job is queued again only for the moment the warm worker takes to
            # pick it up, too short to be polled: the second attempt and the log say it.)
            body = wait_for(c, job_id, timeout=180)
        assert body["status"] == "succeeded" and body["attempts"] == 2, body
        assert time.monotonic() - killed < 120, "taken back by the visibility timeout, not by the lease"
        assert "stopped renewing the lease; sent again" in stack.log.read_text()
    finally:
        stack.stop()
