"""The illumination-invariant loss: invariance, bounds, exactness, guards."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vehicle_pose.loss.invariant import (
    InvariantLoss,
    PhotoTarget,
    invariant_loss,
)
from vehicle_pose.render.renderer import Frame


def _regular(rng: np.random.Generator, k: int) -> np.ndarray:
    while True:
        a = rng.normal(size=(k, k))
        if np.linalg.cond(a) < 1e3:
            return a


def _case(seed: int, n: int, m: int, pixels: int = 400):
    rng = np.random.default_rng(seed)
    f = rng.normal(size=(pixels, n))
    g = rng.normal(size=(pixels, m))
    return rng, f, g


dims = st.tuples(st.integers(1, 3), st.integers(1, 6))


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31), nm=dims)
def test_invariant_to_regular_linear_maps(seed, nm):
    n, m = nm
    rng, f, g = _case(seed, n, m)
    base = invariant_loss(f, g)
    a, b = _regular(rng, n), _regular(rng, m)
    moved = invariant_loss(f @ a.T + rng.normal(size=n), g @ b.T + rng.normal(size=m))
    assert moved == pytest.approx(base, rel=1e-9, abs=1e-12)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31), nm=dims)
def test_bounds(seed, nm):
    n, m = nm
    _, f, g = _case(seed, n, m, pixels=50)
    value = invariant_loss(f, g)
    assert 0.0 <= value <= min(n, m)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31), nm=dims)
def test_zero_iff_exact_linear_relation(seed, nm):
    n, m = nm
    rng, _, g = _case(seed, n, m)
    a = rng.normal(size=(n, m))
    exact = g @ a.T + rng.normal(size=n)
    assert invariant_loss(exact, g) == pytest.approx(0.0, abs=1e-9)
    noisy = exact + 0.1 * rng.normal(size=exact.shape)
    assert invariant_loss(noisy, g) > 1e-4


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31))
def test_one_minus_corr_squared_for_scalars(seed):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=300)
    y = 0.5 * x + rng.normal(size=300)
    r = np.corrcoef(x, y)[0, 1]
    assert invariant_loss(x, y) == pytest.approx(1.0 - r * r, rel=1e-9)


def test_negative_photo_scores_the_same():
    rng = np.random.default_rng(3)
    m = rng.normal(size=(500, 4))
    f = m @ rng.normal(size=4) + 0.3 * rng.normal(size=500)
    assert invariant_loss(1.0 - f, m) == pytest.approx(invariant_loss(f, m), rel=1e-12)


def test_weights_equal_repeated_pixels():
    rng = np.random.default_rng(5)
    f, g = rng.normal(size=(200, 2)), rng.normal(size=(200, 3))
    w = rng.integers(1, 4, size=200)
    assert invariant_loss(f, g, w) == pytest.approx(invariant_loss(np.repeat(f, w, 0), np.repeat(g, w, 0)), rel=1e-10)


def test_singular_model_covariance_is_guarded():
    rng = np.random.default_rng(1)
    f = rng.normal(size=(100, 1))
    g = np.ones((100, 4))
    assert invariant_loss(f, g) == 1.0
    flat = np.column_stack([rng.normal(size=100), np.zeros(100), np.zeros(100), np.zeros(100)])
    assert 0.0 <= invariant_loss(f, flat) <= 1.0


def _frame(attrs: np.ndarray, x0: int, y0: int, width: int, height: int) -> Frame:
    labels = (np.abs(attrs).sum(-1) > 0).astype(np.uint8)
    return Frame(attrs.astype(np.float32), labels, x0, y0, width, height)


def test_bound_loss_matches_direct_formula():
    """The fast silhouette-only evaluation equals the loss over every pixel of the photo."""
    rng = np.random.default_rng(7)
    H, W = 30, 40
    image = rng.random((H, W, 3))
    weights = rng.random((H, W)) + 0.5
    target = PhotoTarget(image, weights, np.ones((H, W), bool))
    window = rng.normal(size=(10, 12, 4))
    window[0, :3] = 0.0
    frame = _frame(window, 5, 7, W, H)
    full = np.zeros((H, W, 5))
    full[7:17, 5:17, 1:] = window
    full[7:17, 5:17, 0] = frame.labels > 0
    direct = invariant_loss(image.reshape(-1, 3), full.reshape(-1, 5), weights.reshape(-1))
    assert InvariantLoss(target)(frame) == pytest.approx(direct, rel=1e-10)


def test_off_screen_model_scores_the_maximum():
    target = PhotoTarget(np.random.default_rng(0).random((20, 20, 1)), np.ones((20, 20)), np.ones((20, 20), bool))
    assert InvariantLoss(target)(Frame.empty(20, 20)) == 1.0


def test_non_finite_attributes_score_the_maximum():
    rng = np.random.default_rng(2)
    g = rng.normal(size=(50, 4))
    g[3, 1] = np.nan
    assert invariant_loss(rng.normal(size=50), g) == 1.0
