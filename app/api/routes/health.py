"""Liveness, readiness and Prometheus metrics."""

from __future__ import annotations

import logging
from typing import Any

import redis
from fastapi import APIRouter, Response
from fastapi.responses import JSONResponse
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from sqlalchemy import text

from app.metrics import registry
from app.problems import MEDIA_TYPE
from core.config import get_settings
from core.db import session_scope
from core.queue import get_celery
from core.storage import get_storage

log = logging.getLogger(__name__)
router = APIRouter(tags=["operations"])


@router.get("/healthz")
async def healthz() -> dict[str, str]:
    """The API process is up (answered on the event loop: it needs no worker thread, so it
    answers even while every thread waits on a dependency)."""
    return {"status": "ok"}


def _check(name: str, results: dict[str, Any], fn: Any) -> None:
    try:
        detail = fn()
        results[name] = {"ok": True, **({"detail": detail} if detail is not None else {})}
    except Exception as exc:  # any failure of a dependency means not ready
        log.warning("readiness check %s failed: %s", name, exc)
        results[name] = {"ok": False, "detail": str(exc) or type(exc).__name__}


def _database() -> None:
    with session_scope() as s:
        s.execute(text("SELECT 1"))


def _broker() -> None:
    client = redis.Redis.from_url(get_settings().broker_url, socket_timeout=2.0, socket_connect_timeout=2.0)
    try:
        client.ping()
    finally:
        client.close()


def _workers() -> str:
    replies = get_celery().control.ping(timeout=1.0) or []
    if not replies:
        raise RuntimeError("no worker answered a ping within 1 s")
    return f"{len(replies)} worker(s)"


@router.get("/readyz")
def readyz() -> JSONResponse:
    """Ready when the database, the broker, the storage and at least one worker answer."""
    checks: dict[str, Any] = {}
    _check("database", checks, _database)
    _check("broker", checks, _broker)
    _check("storage", checks, lambda: get_storage().ping())
    if checks["broker"]["ok"]:
        _check("workers", checks, _workers)
    else:
        checks["workers"] = {"ok": False, "detail": "broker unreachable"}
    if all(c["ok"] for c in checks.values()):
        return JSONResponse({"status": "ready", "checks": checks})
    body = {
        "type": "/problems/not-ready",
        "title": "Service Unavailable",
        "status": 503,
        "detail": "not ready: " + ", ".join(k for k, c in checks.items() if not c["ok"]),
        "instance": "/readyz",
        "checks": checks,
    }
    return JSONResponse(body, status_code=503, media_type=MEDIA_TYPE)


@router.get("/metrics", response_class=Response)
def metrics() -> Response:
    """Prometheus exposition: requests, job durations, queue depth, failures."""
    return Response(generate_latest(registry), media_type=CONTENT_TYPE_LATEST)
