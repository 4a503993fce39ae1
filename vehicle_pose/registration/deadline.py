"""A registration's deadline: checked between loss evaluations, not hoped for from a signal.

A service gives each job a time limit. A signal sent at the limit lands wherever the process
is (in OpenGL, numba, OpenCV, or an ``except`` that catches it) and is often lost; the job then
runs on to a hard kill and loses what it found. Instead the caller passes the moment by which
the registration must end; every search's objective checks it before each evaluation (an
evaluation takes milliseconds; a generation scored at once, a fraction of a second), and so
does each stage's progress report. Past it the
registration raises :class:`~vehicle_pose.errors.OutOfTime` with the best pose the stages
finished so far had found, which the caller can keep.
"""

from __future__ import annotations

import time

import numpy as np
import numpy.typing as npt

from vehicle_pose.errors import OutOfTime
from vehicle_pose.geometry.camera import Camera
from vehicle_pose.search.optimize import Batch, Objective, Optimizer, OptimizeResult, evaluate

__all__ = ["Deadline"]

_clock = time.monotonic  # the clock deadlines are read on (a test may move it)


class Deadline:
    """The moment ``at`` (``time.monotonic()`` seconds) a registration must end by, and the best
    pose its stages have offered (:meth:`offer`), for a photo of ``size`` (width, height)."""

    def __init__(self, at: float, size: tuple[int, int]) -> None:
        self.at = at
        self.size = size
        self.best: Camera | None = None
        self.stage: str | None = None

    def offer(self, camera: Camera, stage: str) -> None:
        """A stage's pose (at any image size of the photo's shape): the best so far."""
        self.best, self.stage = camera, stage

    def check(self) -> None:
        """OutOfTime, carrying the best pose so far at the photo's size, once the moment passed."""
        if _clock() >= self.at:
            best = None if self.best is None else self.best.scaled(*self.size)
            found = f"; the best pose so far is the {self.stage} stage's" if best is not None else ""
            raise OutOfTime(f"the registration reached its deadline{found}", best, self.stage)

    def guard(self, optimizer: Optimizer) -> Optimizer:
        """``optimizer`` with the deadline checked before each evaluation of the objective (before
        each generation, where the optimiser hands it generations whole)."""

        def guarded(fun: Objective, x0: npt.NDArray[np.float64], steps: npt.NDArray[np.float64], *,
                    max_evaluations: int) -> OptimizeResult:
            def checked(x: npt.NDArray[np.float64]) -> float:
                self.check()
                return fun(x)

            def checked_many(xs: npt.NDArray[np.float64]) -> list[float]:
                self.check()
                return evaluate(fun, xs)

            return optimizer(Batch(checked, checked_many), x0, steps, max_evaluations=max_evaluations)

        return guarded
