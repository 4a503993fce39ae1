"""Prepare every model of the service's library into its store (``python -m worker.warm``).

Run by each worker before its pool starts (:func:`worker.tasks.warm_library`), in a process of
its own so that the worker's main process never holds a GL context that its pool children
would inherit. Models already prepared cost a manifest read each; a model that cannot be
prepared is logged and left to be prepared by the first job that needs it.
"""

from __future__ import annotations

import logging
import sys
import time

log = logging.getLogger("worker.warm")


def prepare_model(model_id: str) -> float:
    """Prepare one library model (its levels of detail and exterior passes); the seconds."""
    from core.library import get_library
    from vehicle_pose.render.renderer import Renderer

    t = time.perf_counter()
    get_library().load(model_id).prepare(Renderer())
    return time.perf_counter() - t


def main() -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    from core.library import get_library

    failures = 0
    for model_id in get_library().ids():
        try:
            seconds = prepare_model(model_id)
        except Exception as exc:  # one bad model must not keep the others cold
            failures += 1
            log.warning("cannot prepare model %s: %s: %s", model_id, type(exc).__name__, exc)
            continue
        log.info("model %s ready (%.1f s)", model_id, seconds)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
