"""The Celery application shared by the API (which sends jobs) and the workers (which run them).

Reliability settings: a job is acknowledged only after it finished (``acks_late``) and put back
on the queue when its worker process dies (``reject_on_worker_lost``); each process takes one job
at a time (prefetch 1); soft and hard time limits; the broker's visibility timeout exceeds the
hard limit so a running job is never handed to a second worker.
"""

from __future__ import annotations

import threading
import time
from functools import lru_cache
from typing import Any

from celery import Celery
from kombu.transport.redis import PRIORITY_STEPS, Channel

from core.config import Settings, get_settings

# Connections the API may hold to the broker at once: above its 40 request threads, so that no
# request waits for another's connection (a frozen broker then answers every waiting request
# after one socket timeout, not in waves of ten, Celery's default).
BROKER_POOL_LIMIT = 64

QUEUE = "registrations"

# Message priorities (on Redis the lower number is served first: kombu pops its priority lists
# PRIORITY_STEPS, 0, 3, 6, 9, in that order). A job is sent at PRIORITY_NEW; a job sent again (handed back at a
# stop, taken back from a lost worker) at PRIORITY_AGAIN, so it keeps its place ahead of the
# jobs queued after it.
PRIORITY_AGAIN = 0
PRIORITY_NEW = 3
PRIORITY_LISTS = tuple(f"{QUEUE}{Channel.sep}{p}" if p else QUEUE for p in PRIORITY_STEPS)
"""The Redis lists of the queue, one per priority step (kombu's key for each)."""
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
        broker_pool_limit=BROKER_POOL_LIMIT,
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


class BrokerDown(Exception):
    """The broker is taken for down: a send failed less than the breaker's cool-down ago."""


class Breaker:
    """Sends to the broker, failing fast while it is known to be down.

    After a send fails, every send for the next ``cool_s`` seconds fails at once
    (:class:`BrokerDown`) without touching the broker, so a frozen or lost broker costs one
    socket timeout, not one per request, and holds no thread; then one send at a time tries the
    broker again (the others still fail fast) until one gets through."""

    def __init__(self, cool_s: float) -> None:
        self.cool_s = cool_s
        self._lock = threading.Lock()
        self._failed_at: float | None = None
        self._probing = False

    def send(self, app: Celery, name: str, **kwargs: Any) -> None:
        with self._lock:
            if self._failed_at is not None:
                if self._probing or time.monotonic() - self._failed_at < self.cool_s:
                    raise BrokerDown(f"the broker failed {time.monotonic() - self._failed_at:.1f} s ago")
                self._probing = True
        try:
            app.send_task(name, retry=False, **kwargs)
        except Exception:
            with self._lock:
                self._failed_at, self._probing = time.monotonic(), False
            raise
        with self._lock:
            self._failed_at, self._probing = None, False


@lru_cache
def get_breaker() -> Breaker:
    """The process's breaker in front of the broker (cool-down: one broker socket timeout)."""
    return Breaker(get_settings().broker_timeout_s)
