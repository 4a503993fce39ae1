"""Prometheus metrics: HTTP requests from the API process, job figures read from the database and broker.

Job figures come from the database at scrape time, so they are the same whichever API process
is scraped and need no shared state between workers.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator

import redis
from prometheus_client import CollectorRegistry, Counter, Histogram
from prometheus_client.core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    HistogramMetricFamily,
)
from prometheus_client.registry import Collector
from sqlalchemy import case, func, select
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from core.config import get_settings
from core.db import session_scope
from core.models import JobStatus, Registration
from core.queue import PRIORITY_LISTS

log = logging.getLogger(__name__)

DURATION_BUCKETS = (1.0, 2.0, 3.0, 5.0, 10.0, 20.0, 30.0, 60.0, 120.0, 300.0)

registry = CollectorRegistry()
REQUESTS = Counter(
    "vehicle_pose_http_requests", "HTTP requests answered", ["method", "route", "status"], registry=registry
)
LATENCY = Histogram(
    "vehicle_pose_http_request_duration_seconds",
    "Time to answer an HTTP request",
    ["method", "route"],
    registry=registry,
    buckets=(0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0),
)


class RequestMetrics:
    """ASGI middleware counting requests by route template (not raw path, to bound cardinality)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        code = [500]

        async def send_wrapper(message: Message) -> None:
            if message["type"] == "http.response.start":
                code[0] = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_wrapper)
        finally:
            route = scope.get("route")
            template = getattr(route, "path", None) or "unmatched"
            method = scope["method"]
            REQUESTS.labels(method, template, str(code[0])).inc()
            LATENCY.labels(method, template).observe(time.perf_counter() - start)


def queue_depth() -> int | None:
    """Jobs waiting in the broker's queue, or None when it cannot be reached."""
    try:
        client = redis.Redis.from_url(get_settings().broker_url, socket_timeout=1.0)
        try:
            return sum(int(client.llen(key)) for key in PRIORITY_LISTS)
        finally:
            client.close()
    except redis.RedisError as exc:
        log.warning("queue depth unavailable: %s", exc)
        return None


class JobCollector(Collector):
    """Jobs by status, failures by type and the time-to-result histogram, from the database."""

    def collect(self) -> Iterator[GaugeMetricFamily | CounterMetricFamily | HistogramMetricFamily]:
        jobs = GaugeMetricFamily("vehicle_pose_jobs", "Registration jobs by status", labels=["status"])
        failures = CounterMetricFamily("vehicle_pose_job_failures", "Failed jobs by error type", labels=["type"])
        durations = HistogramMetricFamily(
            "vehicle_pose_job_duration_seconds", "Time from submission to result, finished jobs", labels=["status"]
        )
        with session_scope() as s:
            counts = dict(s.execute(select(Registration.status, func.count()).group_by(Registration.status)).all())
            for st in JobStatus:
                jobs.add_metric([st.value], counts.get(st.value, 0))
            for kind, n in s.execute(
                select(Registration.error_type, func.count())
                .where(Registration.status == JobStatus.failed.value)
                .group_by(Registration.error_type)
            ).all():
                failures.add_metric([kind or "unknown"], n)
            for status in (JobStatus.succeeded.value, JobStatus.failed.value):
                columns = [func.sum(case((Registration.duration_s <= b, 1), else_=0)) for b in DURATION_BUCKETS]
                row = s.execute(
                    select(func.count(), func.coalesce(func.sum(Registration.duration_s), 0.0), *columns).where(
                        Registration.status == status, Registration.duration_s.is_not(None)
                    )
                ).one()
                total, seconds, *cumulative = row
                buckets = [(str(b), int(n or 0)) for b, n in zip(DURATION_BUCKETS, cumulative, strict=True)]
                buckets.append(("+Inf", int(total)))
                durations.add_metric([status], buckets, sum_value=float(seconds))
        yield jobs
        yield failures
        yield durations
        depth = queue_depth()
        if depth is not None:
            yield GaugeMetricFamily("vehicle_pose_queue_depth", "Jobs waiting in the broker queue", value=depth)


registry.register(JobCollector())
