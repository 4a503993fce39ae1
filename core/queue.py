"""The Celery application shared by the API (which sends jobs) and the workers (which run them).

Reliability settings: a job is acknowledged only after it finished (``acks_late``) and put back
on the queue when its worker process dies (``reject_on_worker_lost``); each process takes one job
at a time (prefetch 1); soft and hard time limits; the broker's visibility timeout exceeds the
hard limit so a running job is never handed to a second worker.
"""

from __future__ import annotations

from functools import lru_cache

from celery import Celery

from core.config import Settings, get_settings

QUEUE = "registrations"
TASK = "worker.tasks.register_job"
PREPARE_TASK = "worker.tasks.prepare_model"


def make_celery(settings: Settings) -> Celery:
    app = Celery("vehicle_pose", broker=settings.broker_url)
    app.conf.update(
        task_acks_late=True,
        task_reject_on_worker_lost=True,
        task_acks_on_failure_or_timeout=True,
        worker_prefetch_multiplier=1,
        # A pool process that grew past this (a huge photo's buffers stay in the allocator) is
        # replaced after its job; the job itself is not interrupted.
        worker_max_memory_per_child=settings.worker_max_memory_mb * 1024,
        task_soft_time_limit=settings.job_soft_time_limit_s,
        task_time_limit=settings.job_hard_time_limit_s,
        # Socket timeouts: a broker that stops answering (frozen, partitioned) makes a publish
        # fail within seconds instead of hanging the API's thread forever; they exceed the
        # redis transport's 1 s blocking pop, so an idle worker's poll is not cut short.
        broker_transport_options={
            "visibility_timeout": settings.visibility_timeout_s,
            "socket_timeout": settings.broker_timeout_s,
            "socket_connect_timeout": settings.broker_timeout_s,
        },
        broker_connection_timeout=settings.broker_timeout_s,
        broker_connection_retry_on_startup=True,
        task_default_queue=QUEUE,
        task_routes={TASK: {"queue": QUEUE}, PREPARE_TASK: {"queue": QUEUE}},
        task_ignore_result=True,
        task_serializer="json",
        accept_content=["json"],
        worker_send_task_events=True,
        task_send_sent_event=True,
        worker_hijack_root_logger=False,
    )
    return app


@lru_cache
def get_celery() -> Celery:
    """The process's Celery application, made on first use (the API sends tasks by name; the
    worker's tasks are shared tasks, bound to it when the worker asks for ``worker.app``)."""
    return make_celery(get_settings())
