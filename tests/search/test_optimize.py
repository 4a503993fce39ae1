"""The optimisers: the simplex with restarts minimises, keeps to its budget, and its restarts follow
the last run; CMA-ES walks a narrow valley, keeps to its budget, repeats itself and leaves NumPy's
global generator as it found it; the cross-entropy method returns the middle of a pitted floor;
an objective that scores a generation whole gives the same search."""

from __future__ import annotations

import numpy as np
import pytest

from vehicle_pose.registry import OPTIMIZERS
from vehicle_pose.search.optimize import (
    CMAES,
    Batch,
    Counted,
    CrossEntropy,
    NelderMeadRestarts,
    basis_along,
    evaluate,
)


def valley(x: np.ndarray) -> float:
    """A quadratic valley along (1, 1, ..., 1) / sqrt(n), 300 times narrower across it."""
    d = np.ones(len(x)) / np.sqrt(len(x))
    along = float(d @ (x - 1.0))
    across = (x - 1.0) - along * d
    return along**2 + 300.0**2 * float(across @ across)


def test_minimises_a_round_bowl_to_its_tolerance():
    res = NelderMeadRestarts()(lambda x: float(np.sum((x - 0.3) ** 2)), np.zeros(7), np.full(7, 0.1),
                               max_evaluations=2000)
    np.testing.assert_allclose(res.x, 0.3, atol=0.02)
    assert res.fun < 1e-3


@pytest.mark.parametrize("follow", [False, True])
def test_keeps_to_its_budget(follow):
    calls = []

    def f(x):
        calls.append(1)
        return valley(x)

    res = NelderMeadRestarts(follow=follow)(f, np.zeros(7), np.full(7, 0.1), max_evaluations=150)
    assert len(calls) == res.evaluations <= 150


def test_pattern_moves_double_while_the_loss_falls_and_stop_at_the_first_rise():
    """From x = 0 along (1, 0): 1, 2, 4 improve on f = (x - 5)^2, 8 does not; 4 is kept."""
    counted = Counted(lambda x: float((x[0] - 5.0) ** 2 + x[1] ** 2))
    counted(np.zeros(2))
    NelderMeadRestarts().pattern_search(counted, np.zeros(2), np.array([1.0, 0.0]), max_evaluations=100)
    assert counted.count == 1 + 4
    np.testing.assert_allclose(counted.best_x, [4.0, 0.0])


def test_pattern_moves_keep_to_the_budget():
    counted = Counted(lambda x: -float(x[0]))
    counted(np.zeros(1))
    NelderMeadRestarts(pattern_moves=10).pattern_search(counted, np.zeros(1), np.ones(1), max_evaluations=3)
    assert counted.count == 3


def test_basis_along_a_direction_is_orthonormal_and_starts_with_it():
    d = np.array([0.3, -1.0, 0.2, 0.0, 2.0, 0.1, -0.4])
    q = basis_along(d)
    np.testing.assert_allclose(q.T @ q, np.eye(7), atol=1e-12)
    np.testing.assert_allclose(abs(q[:, 0] @ d) / np.linalg.norm(d), 1.0, atol=1e-12)


def test_runs_stop_at_their_evaluation_cap_and_the_search_restarts():
    """Each simplex run ends after ``run_evaluations``; the search restarts from its best point
    and still converges. Uncapped, one run (and one confirming restart) does the work."""
    calls: list[int] = []
    starts: list[int] = []
    optimizer = NelderMeadRestarts(run_evaluations=40, max_restarts=30, follow=False)

    def bowl(x: np.ndarray) -> float:
        calls.append(1)
        return float(np.sum((x - 2.0) ** 2))

    import vehicle_pose.search.optimize as optimize_module

    real_minimize = optimize_module.minimize

    def spy(*args, **kwargs):
        starts.append(len(calls))
        assert kwargs["options"]["maxfev"] <= 40
        return real_minimize(*args, **kwargs)

    optimize_module.minimize = spy
    try:
        res = optimizer(bowl, np.zeros(7), np.full(7, 0.5), max_evaluations=1500)
    finally:
        optimize_module.minimize = real_minimize
    runs = np.diff(starts + [len(calls)])
    assert len(starts) >= 4 and runs.max() <= 41  # scipy may finish the iteration it is in
    assert res.fun < 1e-2  # from 28
    uncapped = NelderMeadRestarts(run_evaluations=0)(lambda x: float(np.sum((x - 2.0) ** 2)), np.zeros(7),
                                                     np.full(7, 0.5), max_evaluations=1500)
    assert uncapped.restarts < len(starts) - 1


def rotated_valley(x: np.ndarray) -> float:
    """A quadratic valley 100 times narrower across than along, along no axis, minimum at 0.7."""
    q = np.linalg.qr(np.arange(1.0, 50.0).reshape(7, 7) ** 0.5)[0]
    z = q.T @ (x - 0.7)
    return float(z[0] ** 2 + 100.0**2 * np.sum(z[1:] ** 2))


def test_cma_es_walks_a_narrow_valley_to_its_minimum_where_the_simplex_stops_short():
    res = CMAES()(rotated_valley, np.zeros(7), np.full(7, 0.3), max_evaluations=4000)
    np.testing.assert_allclose(res.x, 0.7, atol=1e-3)
    assert res.fun < 1e-5 and res.evaluations <= 4000 and OPTIMIZERS.get("cma-es") is CMAES
    simplex = NelderMeadRestarts()(rotated_valley, np.zeros(7), np.full(7, 0.3), max_evaluations=4000)
    assert simplex.fun > 1.0


def test_cma_es_keeps_to_its_budget_and_never_ends_above_its_start():
    calls = []

    def f(x):
        calls.append(1)
        return rotated_valley(x) if len(calls) == 1 else 1e9  # everything but the start is worse

    res = CMAES()(f, np.zeros(7), np.full(7, 0.3), max_evaluations=100)
    assert len(calls) == res.evaluations <= 100
    np.testing.assert_array_equal(res.x, np.zeros(7))
    for budget in (100, 105, 9):
        # Whole generations of 9 (4 + 3 ln 7) samples after the start, never past the budget.
        res = CMAES()(rotated_valley, np.zeros(7), np.full(7, 0.3), max_evaluations=budget)
        assert budget - 9 < res.evaluations <= budget


def test_cma_es_repeats_itself_and_restores_the_global_generator():
    np.random.seed(11)
    expected = np.random.rand()
    np.random.seed(11)
    a = CMAES()(rotated_valley, np.zeros(7), np.full(7, 0.3), max_evaluations=300)
    assert np.random.rand() == expected
    b = CMAES()(rotated_valley, np.zeros(7), np.full(7, 0.3), max_evaluations=300)
    np.testing.assert_array_equal(a.x, b.x)
    c = CMAES(seed=2)(rotated_valley, np.zeros(7), np.full(7, 0.3), max_evaluations=300)
    assert not np.array_equal(a.x, c.x)


def pitted(x: np.ndarray) -> float:
    """A broad bowl about 0.5 with a grid of narrow pits 0.1 apart, one of them, at -0.1 off
    the bowl's floor, lower than the pit at the bowl's centre."""
    bowl = float(np.sum((x - 0.5) ** 2))
    pits = -0.05 * float(np.prod(np.cos(np.pi * (x - 0.5) / 0.05) ** 20))
    return bowl + pits


def test_cross_entropy_returns_the_middle_of_a_pitted_floor():
    res = CrossEntropy(population=100, elite=10)(pitted, np.zeros(3), np.full(3, 0.5), max_evaluations=801)
    np.testing.assert_allclose(res.x, 0.5, atol=0.05)
    assert res.fun == pytest.approx(pitted(res.x))
    assert res.evaluations == 801


def test_cross_entropy_keeps_to_its_budget_repeats_itself_and_checks_its_elite():
    calls = []

    def counted(x: np.ndarray) -> float:
        calls.append(np.array(x))
        return float(np.sum(x**2))

    first = CrossEntropy(population=20, elite=4, seed=3)(counted, np.ones(2), np.ones(2), max_evaluations=70)
    assert first.evaluations == len(calls) == 61  # three generations of 20 and their mean
    np.testing.assert_array_equal(calls[0], np.ones(2))  # the start is the first sample
    again = CrossEntropy(population=20, elite=4, seed=3)(counted, np.ones(2), np.ones(2), max_evaluations=70)
    np.testing.assert_array_equal(first.x, again.x)
    with pytest.raises(ValueError, match="elite"):
        CrossEntropy(population=10, elite=11)


@pytest.mark.parametrize("optimizer", [CrossEntropy(population=20, elite=4, seed=5), CMAES(sigma=0.5, seed=2)])
def test_an_objective_that_scores_generations_whole_gives_the_same_search(optimizer):
    """A :class:`Batch` objective is handed each generation at once (one call of ``many`` per
    generation after the start), and the search ends exactly where one point at a time ends."""
    sizes: list[int] = []

    def many(xs: np.ndarray) -> list[float]:
        sizes.append(len(xs))
        return [valley(x) for x in xs]

    alone = optimizer(valley, np.zeros(4), np.full(4, 0.5), max_evaluations=200)
    together = optimizer(Batch(valley, many), np.zeros(4), np.full(4, 0.5), max_evaluations=200)
    np.testing.assert_array_equal(together.x, alone.x)
    assert (together.fun, together.evaluations) == (alone.fun, alone.evaluations)
    assert len(sizes) >= 2 and sum(sizes) >= together.evaluations - 2 and max(sizes) > 1


def test_counted_many_counts_and_keeps_the_best_as_one_by_one():
    xs = np.array([[3.0], [1.0], [2.0], [1.0]])
    one = Counted(lambda x: float(x[0]))
    many = Counted(Batch(lambda x: float(x[0]), lambda xs: [float(x[0]) for x in xs]))
    assert [one(x) for x in xs] == many.many(xs) == evaluate(lambda x: float(x[0]), xs)
    assert (one.count, one.best_f) == (many.count, many.best_f) == (4, 1.0)
    np.testing.assert_array_equal(one.best_x, many.best_x)
