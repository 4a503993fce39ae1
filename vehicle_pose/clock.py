"""Where the engine's seconds go, when someone asks: an opt-in clock of the time spent per kind
of work (drawing and reading back renders, the shading losses, the chamfers, template matching,
GrabCut, the photo's edges).

Off by default, and then nearly free: a timed call looks up one context variable. The speed
benchmark (``bench/stages.py``) turns it on around a registration with :func:`clocked`. A timed
call made inside another timed call is charged to the outer one only, so the kinds add up to
no more than the time they cover. While a clock runs the renderer finishes each draw before
reading it back, which takes away the overlap of drawing and reading: clocked runs are slightly
slower than plain ones.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field
from typing import Any, TypeVar, cast

__all__ = ["Clock", "clocked", "current", "timed"]

F = TypeVar("F", bound=Callable[..., Any])


@dataclass
class Clock:
    """Seconds and calls per kind of work, since :func:`clocked` made it."""

    seconds: dict[str, float] = field(default_factory=dict)
    calls: dict[str, int] = field(default_factory=dict)
    busy: bool = False

    def add(self, kind: str, seconds: float, calls: int = 1) -> None:
        self.seconds[kind] = self.seconds.get(kind, 0.0) + seconds
        self.calls[kind] = self.calls.get(kind, 0) + calls


_CLOCK: ContextVar[Clock | None] = ContextVar("vehicle_pose_clock", default=None)


def current() -> Clock | None:
    """The clock running in this context, if any."""
    return _CLOCK.get()


@contextmanager
def clocked() -> Iterator[Clock]:
    """Run a clock over the ``with`` block (this thread's context) and yield it."""
    clock = Clock()
    token = _CLOCK.set(clock)
    try:
        yield clock
    finally:
        _CLOCK.reset(token)


def timed(kind: str) -> Callable[[F], F]:
    """Charge the decorated function's seconds to ``kind`` on the running clock, if one runs and
    no timed call encloses this one."""

    def wrap(fn: F) -> F:
        @functools.wraps(fn)
        def inner(*args: Any, **kwargs: Any) -> Any:
            clock = _CLOCK.get()
            if clock is None or clock.busy:
                return fn(*args, **kwargs)
            clock.busy = True
            t = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                clock.busy = False
                clock.add(kind, time.perf_counter() - t)

        return cast(F, inner)

    return wrap
