"""The Celery workers: ``celery -A worker worker`` runs them.

Each pool process has one headless EGL context (made on first use, after the fork). The Celery
application is made when the worker asks for ``worker.app``, not on import.
"""

from __future__ import annotations

from typing import Any


def __getattr__(name: str) -> Any:
    if name == "app":
        import worker.tasks  # noqa: F401  (the tasks are shared tasks: they bind to the app)
        from core.queue import get_celery

        return get_celery()
    raise AttributeError(f"module 'worker' has no attribute {name!r}")
