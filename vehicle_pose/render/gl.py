"""The one place that creates an OpenGL context: headless EGL, lazily, once per process.

A context made before ``fork()`` is unusable in the child (and can hang it), so the context is
keyed by process id: a forked child that asks for one gets its own. Nothing happens at import.
"""

from __future__ import annotations

import ctypes
import functools
import os
import threading

import moderngl

from vehicle_pose.errors import RenderError

__all__ = ["get_context", "gl_library", "release_context", "thread_context"]

_lock = threading.Lock()
_state: dict[str, object] = {}


def get_context(backend: str = "egl") -> moderngl.Context:
    """The process's standalone OpenGL 3.3+ context, created on first use.

    Parameters
    ----------
    backend : str
        moderngl/glcontext backend; ``"egl"`` for headless rendering (Mesa llvmpipe on CPU,
        or the NVIDIA EGL driver on a GPU machine).

    Raises
    ------
    RenderError
        No context could be created (no EGL driver, no OpenGL 3.3).
    """
    with _lock:
        ctx = _state.get("ctx")
        if ctx is not None and _state.get("pid") == os.getpid():
            return ctx  # type: ignore[return-value]
        try:
            ctx = moderngl.create_context(standalone=True, backend=backend, require=330)  # type: ignore[arg-type]
        except Exception as exc:  # glcontext raises plain Exceptions for driver failures
            raise RenderError(f"cannot create a headless OpenGL context ({backend}): {exc}") from None
        _state.update(ctx=ctx, pid=os.getpid())
        return ctx


_threads = threading.local()


def thread_context(backend: str = "egl") -> moderngl.Context:
    """A further standalone context, current on the calling thread and kept for it (made again
    after a fork): for work that draws in several threads at once, each with its own context
    (the exterior pass on a CPU rasteriser). Raises :class:`RenderError` as :func:`get_context`."""
    ctx = getattr(_threads, "ctx", None)
    if ctx is not None and getattr(_threads, "pid", None) == os.getpid():
        return ctx  # type: ignore[no-any-return]
    try:
        ctx = moderngl.create_context(standalone=True, backend=backend, require=330)  # type: ignore[arg-type]
    except Exception as exc:  # glcontext raises plain Exceptions for driver failures
        raise RenderError(f"cannot create a headless OpenGL context ({backend}): {exc}") from None
    _threads.ctx, _threads.pid = ctx, os.getpid()
    return ctx


def release_context() -> None:
    """Release this process's context (if any); the next :func:`get_context` makes a new one."""
    with _lock:
        ctx = _state.pop("ctx", None)
        pid = _state.pop("pid", None)
        if ctx is not None and pid == os.getpid():
            ctx.release()  # type: ignore[attr-defined]


@functools.cache
def gl_library() -> ctypes.CDLL | None:
    """The OpenGL dispatch library (libglvnd's ``libOpenGL``, else ``libGL``) for the calls made
    through ctypes (those moderngl does not make, or makes holding Python's lock); they go to
    the context current on the calling thread. None where neither loads."""
    for name in ("libOpenGL.so.0", "libGL.so.1"):
        try:
            return ctypes.CDLL(name)
        except OSError:
            continue
    return None
