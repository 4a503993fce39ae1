"""Celery tasks: deserialise, call the job runner, retry transient failures."""

from __future__ import annotations

from celery import Task
from celery.exceptions import SoftTimeLimitExceeded
from celery.signals import worker_process_init

from app.core.db import get_engine

from .celery_app import TASK, celery_app
from .jobs import Retry, requeue, run_job

RETRY_DELAY_S = 2


@worker_process_init.connect
def _fresh_process(**_: object) -> None:
    """A pool process starts with its own database connections (the GL context comes lazily)."""
    get_engine.cache_clear()


@celery_app.task(name=TASK, bind=True, max_retries=None)
def register_job(self: Task, job_id: str) -> str:
    """Register the job's photo; the attempt count lives in the job record, not in Celery."""
    try:
        return run_job(job_id, timeouts=(SoftTimeLimitExceeded,))
    except Retry as exc:
        requeue(job_id)
        raise self.retry(countdown=RETRY_DELAY_S, exc=exc) from exc
