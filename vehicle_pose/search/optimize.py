"""Derivative-free minimisers of the registration loss (method.md §5, step 3).

The default is the paper's downhill simplex (Nelder-Mead) restarted at the best point with a
fresh simplex until a restart no longer improves. Any callable with the :class:`Optimizer`
signature can replace it.

An objective may also score many points at once (a :class:`Batch`, whose ``many`` draws a
population's poses in one pass): the population methods (:class:`CrossEntropy`, :class:`CMAES`)
hand it each generation whole (:func:`evaluate`); the result is the same as one point at a time.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt
from scipy.optimize import minimize

from vehicle_pose.registry import OPTIMIZERS


def _cma() -> Any:
    """The ``cma`` package, imported on first use (0.5 s: it loads scipy.stats), so that a
    registration that never runs CMA-ES does not pay for it."""
    with warnings.catch_warnings():
        # The package warns on import when matplotlib (its plotting) is missing.
        warnings.simplefilter("ignore")
        import cma

    return cma


__all__ = [
    "OptimizeResult", "Optimizer", "NelderMeadRestarts", "Powell", "CMAES", "CrossEntropy", "Counted", "basis_along",
    "make_optimizer", "Batch", "evaluate",
]

FloatArray = npt.NDArray[np.float64]
Objective = Callable[[FloatArray], float]


class Batch:
    """An objective that scores one point (``one``) and many at once (``many``: the rows of an
    array to their values, each the same as ``one``'s)."""

    def __init__(self, one: Objective, many: Callable[[FloatArray], list[float]]) -> None:
        self.one, self.many = one, many

    def __call__(self, x: FloatArray) -> float:
        return self.one(x)


def evaluate(fun: Objective, xs: FloatArray) -> list[float]:
    """``fun`` at each row of ``xs``, in order: at once where it is a :class:`Batch`."""
    if isinstance(fun, Batch):
        return [float(v) for v in fun.many(xs)]
    return [float(fun(x)) for x in xs]


@dataclass(frozen=True)
class OptimizeResult:
    """Best point, its value, the number of objective evaluations and of restarts."""

    x: FloatArray
    fun: float
    evaluations: int
    restarts: int


class Optimizer(Protocol):
    def __call__(self, fun: Objective, x0: FloatArray, steps: FloatArray, *, max_evaluations: int) -> OptimizeResult:
        """Minimise ``fun`` from ``x0``; ``steps`` gives the scale of each coordinate."""
        ...


class Counted:
    """Counts evaluations and remembers the best point seen."""

    def __init__(self, fun: Objective) -> None:
        self.fun = fun
        self.count = 0
        self.best_x: FloatArray | None = None
        self.best_f = np.inf

    def __call__(self, x: FloatArray) -> float:
        return self._keep(x, float(self.fun(x)))

    def many(self, xs: FloatArray) -> list[float]:
        """The values at the rows of ``xs`` (:func:`evaluate`), counted and kept as one by one."""
        return [self._keep(x, f) for x, f in zip(xs, evaluate(self.fun, xs), strict=True)]

    def _keep(self, x: FloatArray, f: float) -> float:
        """Count one evaluation, ``f`` at ``x``, and remember it if it is the best so far."""
        self.count += 1
        if f < self.best_f:
            self.best_f, self.best_x = f, np.array(x, dtype=np.float64)
        return f

    def result(self, restarts: int = 0) -> OptimizeResult:
        """The best point seen, its value and the evaluation count."""
        assert self.best_x is not None
        return OptimizeResult(self.best_x, self.best_f, self.count, restarts)


@dataclass(frozen=True)
class NelderMeadRestarts:
    """Nelder-Mead, restarted at the best point until a restart improves by less than ``min_gain``.

    Parameters
    ----------
    max_restarts : int
        Restarts after the first run.
    run_evaluations : int
        One run stops after this many evaluations and the search restarts from its best point
        (0: a run goes on until its own tests stop it). A long simplex run in seven dimensions
        flattens along the valley it follows and crawls; a fresh simplex, with its first edge
        along the way the last run went (``follow``), moves on
        (docs/decisions/0009-simplex-restarts.md).
    min_gain : float
        A restart that lowers the loss by less stops the search.
    xtol : float
        Simplex size (in units of ``steps``) at which one run stops.
    ftol : float
        Spread of loss values in the simplex at which one run stops.
    patience : int
        A run also stops when its best value has improved by less than ``ftol`` over this many
        iterations: pixel quantisation keeps the loss from ever becoming smooth enough for
        the simplex's own tests. 32 rather than 16: with 16 the simplex stopped about 1 px
        short on some synthetic cases whose true pose scored far lower.
    shrink : float
        Each restart's simplex is this fraction of the previous one's.
    adaptive : bool
        Use dimension-dependent simplex coefficients (Gao and Han, 2012).
    follow : bool
        Before each restart, step along the previous run's displacement (doubling while the
        loss falls, at most ``pattern_moves`` steps), and give the restart's simplex its first
        edge along that displacement: a run that crawled along a diagonal valley hands its
        direction on instead of starting again from axis-aligned edges.
    pattern_moves : int
    """

    max_restarts: int = 20
    run_evaluations: int = 60
    min_gain: float = 1e-5
    xtol: float = 0.05
    ftol: float = 1e-5
    shrink: float = 0.7
    adaptive: bool = False
    patience: int = 32
    follow: bool = True
    pattern_moves: int = 4

    def __call__(self, fun: Objective, x0: FloatArray, steps: FloatArray, *, max_evaluations: int) -> OptimizeResult:
        counted = Counted(fun)
        x = np.asarray(x0, dtype=np.float64)
        s = np.asarray(steps, dtype=np.float64)
        best = counted(x)
        restarts = -1
        scale = 1.0
        dim = len(x)
        basis = np.eye(dim)
        moved: FloatArray | None = None
        while restarts < self.max_restarts and counted.count < max_evaluations:
            restarts += 1
            before = best
            if self.follow and moved is not None and np.any(moved):
                # Pattern moves along the last run's displacement, doubling while they improve,
                # then a simplex with its first edge along it.
                self.pattern_search(counted, x, moved * s, max_evaluations)
                basis = basis_along(moved)
            # Search in coordinates scaled by the steps, so one tolerance suits every parameter.
            origin = counted.best_x.copy()  # type: ignore[union-attr]
            history: list[float] = []

            def stall(intermediate_result: object) -> None:
                history.append(counted.best_f)
                settled = len(history) > max(self.patience, 2 * (dim + 1))
                if settled and history[-1 - self.patience] - history[-1] < self.ftol:
                    raise StopIteration

            left = max_evaluations - counted.count
            if left > 0:
                minimize(
                    lambda z: counted(origin + (basis @ z) * s),
                    np.zeros(dim),
                    method="Nelder-Mead",
                    callback=stall,
                    options={
                        "initial_simplex": np.vstack([np.zeros(dim), scale * np.eye(dim)]),
                        "xatol": self.xtol,
                        "fatol": self.ftol,
                        "maxfev": left if self.run_evaluations <= 0 else min(self.run_evaluations, left),
                        "adaptive": self.adaptive,
                    },
                )
            assert counted.best_x is not None
            moved = (counted.best_x - x) / s
            x, best = counted.best_x, counted.best_f
            # The first run is not a restart: only a restart that fails to improve ends the search.
            if restarts > 0 and before - best < self.min_gain:
                break
            scale *= self.shrink
        return counted.result(max(restarts, 0))

    def pattern_search(self, counted: Counted, x: FloatArray, step: FloatArray, max_evaluations: int) -> None:
        """Steps from ``x`` along ``step``, doubling while the loss falls (at most
        ``pattern_moves`` steps, within the budget); ``counted`` keeps the best point."""
        best = counted.best_f
        k = 1.0
        for _ in range(self.pattern_moves):
            if counted.count >= max_evaluations or counted(x + k * step) >= best:
                return
            best = counted.best_f
            k *= 2.0


def basis_along(d: FloatArray) -> FloatArray:
    """An orthonormal basis (columns) whose first vector is ``d`` normalised."""
    q, _ = np.linalg.qr(np.column_stack([d / np.linalg.norm(d), np.eye(len(d))]))
    return q[:, : len(d)]


@dataclass(frozen=True)
class Powell:
    """SciPy's Powell line-search method, for comparison."""

    xtol: float = 0.05
    ftol: float = 1e-5

    def __call__(self, fun: Objective, x0: FloatArray, steps: FloatArray, *, max_evaluations: int) -> OptimizeResult:
        counted = Counted(fun)
        s = np.asarray(steps, dtype=np.float64)
        x0 = np.asarray(x0, dtype=np.float64)
        counted(x0)
        minimize(
            lambda z: counted(x0 + z * s),
            np.zeros_like(x0),
            method="Powell",
            options={"xtol": self.xtol, "ftol": self.ftol, "maxfev": max_evaluations, "direc": np.eye(len(x0))},
        )
        return counted.result()


@dataclass(frozen=True)
class CMAES:
    """The covariance matrix adaptation evolution strategy (Hansen's ``cma`` package).

    It learns the local covariance of good steps, so it walks along a narrow diagonal valley
    that stops a simplex: near-frontal and near-rear views with a short lens, where
    elevation, vertical position, scale and focal length trade against each other, leave the
    simplex short of a pose that scores far lower (docs/decisions/0007-no-hint-search.md).

    Parameters
    ----------
    sigma : float
        Initial standard deviation, in units of ``steps``.
    popsize : int
        Samples per generation (0: the package's default, 4 + 3 ln(dim), 9 in seven dimensions).
    seed : int
        Seed of the sampling: the same call gives the same result.
    xtol, ftol : float
        Stop when the steps (units of ``steps``) or the spread of recent values are this small.
    """

    sigma: float = 0.5
    popsize: int = 0
    seed: int = 1
    xtol: float = 1e-3
    ftol: float = 1e-6

    def __call__(self, fun: Objective, x0: FloatArray, steps: FloatArray, *, max_evaluations: int) -> OptimizeResult:
        counted = Counted(fun)
        s = np.asarray(steps, dtype=np.float64)
        x0 = np.asarray(x0, dtype=np.float64)
        counted(x0)
        options: dict[str, object] = {
            "verbose": -9,
            "tolx": self.xtol,
            "tolfun": self.ftol,
            "seed": self.seed,
        }
        if self.popsize > 0:
            options["popsize"] = self.popsize
        # The package seeds NumPy's global generator; the caller's state is put back.
        state = np.random.get_state()
        try:
            es = _cma().CMAEvolutionStrategy(np.zeros(len(x0)), self.sigma, options)
            # Only whole generations, so the budget holds exactly.
            while not es.stop() and counted.count + es.popsize <= max_evaluations:
                zs = es.ask()
                es.tell(zs, counted.many(np.array([x0 + np.asarray(z) * s for z in zs])))
        finally:
            np.random.set_state(state)
        return counted.result()


@dataclass(frozen=True)
class CrossEntropy:
    """The cross-entropy method: each generation samples ``population`` points from a Gaussian
    and refits its mean and spread to the ``elite`` best; the result is the final mean.

    The mean of the best rather than the best point: where a cost's minimum is a broad floor
    pitted with local minima of about the same depth (an edge chamfer on a real photo, where
    every reflection makes an edge), the lowest sample is one pit chosen by chance, and the
    elite's mean lies near the middle of the floor (docs/decisions/0012-structure-first.md).

    Parameters
    ----------
    population : int
        Samples per generation; the first generation's first sample is ``x0`` itself.
    elite : int
        The best samples the next generation is fitted to.
    sigma : float
        The first generation's standard deviation, in units of ``steps``.
    seed : int
        Seed of the sampling: the same call gives the same result.
    """

    population: int = 100
    elite: int = 10
    sigma: float = 1.0
    seed: int = 0

    def __post_init__(self) -> None:
        if not 1 <= self.elite <= self.population:
            raise ValueError(f"elite must be in [1, population={self.population}], not {self.elite}")

    def __call__(self, fun: Objective, x0: FloatArray, steps: FloatArray, *, max_evaluations: int) -> OptimizeResult:
        counted = Counted(fun)
        rng = np.random.default_rng(self.seed)
        mean = np.asarray(x0, dtype=np.float64).copy()
        spread = self.sigma * np.asarray(steps, dtype=np.float64)
        generations = max(1, (max_evaluations - 1) // self.population)
        for g in range(generations):
            xs = mean + rng.standard_normal((self.population, mean.size)) * spread
            if g == 0:
                xs[0] = mean
            values = np.array(counted.many(xs))
            best = xs[np.argsort(values, kind="stable")[: self.elite]]
            mean, spread = best.mean(axis=0), best.std(axis=0)
        return OptimizeResult(mean, counted(mean), counted.count, generations - 1)


OPTIMIZERS.register("nelder-mead")(NelderMeadRestarts)
OPTIMIZERS.register("powell")(Powell)
OPTIMIZERS.register("cma-es")(CMAES)


def make_optimizer(name: str) -> Optimizer:
    """A fresh optimiser called ``name``; ValueError for an unknown name."""
    optimizer: Optimizer = OPTIMIZERS.get(name)()
    return optimizer
