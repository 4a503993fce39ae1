"""Celery tasks: deserialise, call the job runner, retry transient failures."""

from __future__ import annotations

import logging
import subprocess
import sys
import threading
from typing import Any

from celery import Task, shared_task
from celery.exceptions import SoftTimeLimitExceeded, TimeLimitExceeded
from celery.signals import worker_init, worker_process_init, worker_ready, worker_shutdown

from core.config import get_settings
from core.db import get_engine
from core.queue import PREPARE_TASK, PRIORITY_AGAIN, TASK
from worker.jobs import Retry, fail_job, reap_stale_jobs, requeue, resend_handed_back, run_job

log = logging.getLogger(__name__)

RETRY_DELAY_S = 2
MAX_RETRIES = 12


@worker_process_init.connect
def _fresh_process(**_: object) -> None:
    """A pool process starts with its own database connections (the GL context comes lazily).

    The parent's pool (its lease reaper's connections) is dropped without closing: closing a
    connection inherited through the fork would end it for the parent too."""
    get_engine().dispose(close=False)
    get_engine.cache_clear()


_reaper_stop = threading.Event()


@worker_ready.connect
def start_lease_reaper(sender: Any = None, **_: object) -> None:
    """In the worker's main process: send again the jobs handed back to the queue
    (:func:`worker.jobs.resend_handed_back`), then every third of ``lease_s`` the running jobs
    whose worker stopped renewing its lease (:func:`worker.jobs.reap_stale_jobs`)."""
    if sender is None:
        return
    settings, app = get_settings(), sender.app

    def send_again(job_id: str) -> None:
        app.send_task(TASK, args=[job_id], task_id=job_id, priority=PRIORITY_AGAIN)

    try:
        resend_handed_back(send_again)
    except Exception as exc:  # database or broker away: their messages come back in time anyway
        log.warning("cannot send the handed-back jobs again: %s: %s", type(exc).__name__, exc)

    def loop() -> None:
        while not _reaper_stop.wait(settings.lease_s / 3.0):
            try:
                reap_stale_jobs(settings, send_again)
            except Exception as exc:  # database or broker away: the next round tries again
                log.warning("lease reaper: %s: %s", type(exc).__name__, exc)

    _reaper_stop.clear()
    threading.Thread(target=loop, name="lease-reaper", daemon=True).start()


@worker_shutdown.connect
def _stop_lease_reaper(**_: object) -> None:
    _reaper_stop.set()


@worker_init.connect
def warm_library(**_: object) -> None:
    """Before the pool starts, prepare every library model into the store (worker.warm), so no
    job pays for preparing a model; a failure is logged and the worker starts all the same."""
    timeout = get_settings().warm_timeout_s
    try:
        done = subprocess.run([sys.executable, "-m", "worker.warm"], timeout=timeout, check=False)
    except subprocess.TimeoutExpired:
        log.warning("preparing the library took over %s s; the rest is prepared by the jobs", timeout)
        return
    if done.returncode != 0:
        log.warning("some library models could not be prepared (exit %s); see the log above", done.returncode)


@shared_task(name=PREPARE_TASK, ignore_result=True)
def prepare_model(model_id: str) -> None:
    """Prepare a model that was just uploaded (sent by the API; best effort)."""
    from worker.warm import prepare_model as prepare

    try:
        log.info("model %s prepared (%.1f s)", model_id, prepare(model_id))
    except Exception as exc:  # the model stays usable: its first job prepares it
        log.warning("cannot prepare model %s: %s: %s", model_id, type(exc).__name__, exc)


class RegistrationTask(Task):
    """Records in the job how a run ended that never reached the job runner's own handling.

    When the pool process running a job dies (SIGKILL, out of memory), the worker's main process
    sends the job again after ``RETRY_DELAY_S`` (``retry_on_worker_lost``) and :meth:`on_retry`
    marks its record ``queued`` (stage ``retrying``) meanwhile, instead of leaving it ``running``
    with frozen progress until a process takes it.
    """

    retry_on_worker_lost = True
    default_retry_delay = RETRY_DELAY_S

    def on_retry(self, exc: BaseException, task_id: str, args: Any, kwargs: Any, einfo: Any) -> None:
        job_id = args[0] if args else kwargs.get("job_id")
        if job_id is None:
            return
        try:
            requeue(job_id)
        except Exception:  # the database may be down: the retry still happens
            log.warning("cannot mark job %s for retry", job_id)

    def on_failure(self, exc: BaseException, task_id: str, args: Any, kwargs: Any, einfo: Any) -> None:
        # Called in the worker's main process after a hard time limit killed the pool process,
        # and in the pool process when retries ran out.
        job_id = args[0] if args else kwargs.get("job_id")
        if job_id is None:
            return
        if isinstance(exc, TimeLimitExceeded):
            limit = self.time_limit or self.app.conf.task_time_limit
            reason = ("timeout", f"the registration was stopped at the hard time limit of {limit} s")
        else:
            reason = ("internal-error", f"gave up: {type(exc).__name__}: {exc}")
        try:
            fail_job(job_id, *reason)
        except Exception:  # the database itself may be what failed
            log.exception("cannot record the failure of job %s", job_id)


@shared_task(name=TASK, bind=True, base=RegistrationTask, max_retries=MAX_RETRIES)
def register_job(self: Task, job_id: str) -> str:
    """Register the job's photo; attempts that really ran are counted in the job record."""
    try:
        return run_job(job_id, timeouts=(SoftTimeLimitExceeded,))
    except Retry as exc:
        try:
            requeue(job_id)
        except Exception:  # the database may be down: the retry still happens
            log.warning("cannot mark job %s for retry", job_id)
        delay = RETRY_DELAY_S * 2 ** min(self.request.retries, 4)
        raise self.retry(countdown=delay, exc=exc) from exc
