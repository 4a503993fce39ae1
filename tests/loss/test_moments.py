"""The compiled moment sums and loss agree with the matrix form, whatever the memory layout."""

from __future__ import annotations

import numpy as np
import pytest

from vehicle_pose.loss.invariant import (
    InvariantLoss,
    PartsInvariantLoss,
    PhotoTarget,
    normal_channels,
    part_channels,
)
from vehicle_pose.render.renderer import Frame


@pytest.mark.parametrize("n,weighted", [(1, False), (3, False), (1, True), (3, True)])
def test_parts_loss_equals_the_channel_matrix_form(n, weighted):
    """The per-material moment gathering gives the loss of the explicit one-hot channels."""
    rng = np.random.default_rng(11 + n)
    H, W = 40, 50
    image = rng.random((H, W, n))
    weights = rng.random((H, W)) + 0.5 if weighted else np.ones((H, W))
    target = PhotoTarget(image, weights, np.ones((H, W), bool))
    attrs = rng.random((20, 30, 4)).astype(np.float32)
    labels = rng.choice([0, 1, 2, 4, 5], size=(20, 30), p=[0.2, 0.5, 0.15, 0.1, 0.05]).astype(np.uint8)
    attrs[labels == 0] = 0.0
    frame = Frame(attrs, labels, 8, 6, W, H)
    expected = InvariantLoss(target, channels=part_channels)(frame)
    assert PartsInvariantLoss(target)(frame) == pytest.approx(expected, rel=1e-10, abs=1e-13)
    # One material only: its indicator is the coverage channel.
    frame1 = Frame(attrs, (labels > 0).astype(np.uint8), 8, 6, W, H)
    assert PartsInvariantLoss(target)(frame1) == pytest.approx(InvariantLoss(target, channels=part_channels)(frame1),
                                                               rel=1e-10)
    assert PartsInvariantLoss(target)(Frame.empty(W, H)) == float(min(n, 10))


def test_compiled_moments_take_any_memory_layout_and_agree_with_the_matrix_form():
    """Read-back windows may be views (flipped rows, a channel slice); the compiled pass reads
    them as they are and gives the loss of the explicit channel matrix."""
    rng = np.random.default_rng(5)
    H, W = 36, 44
    target = PhotoTarget(rng.random((H, W, 1)), np.ones((H, W)), np.ones((H, W), bool))
    big = rng.random((24, 30, 6)).astype(np.float32)
    attrs = big[::-1, :, 1:5]
    labels = rng.choice([0, 1, 3], size=(24, 30), p=[0.3, 0.5, 0.2]).astype(np.uint8)[::-1]
    frame = Frame(attrs, labels, 9, 4, W, H)
    assert not attrs.flags.c_contiguous
    general = InvariantLoss(target, channels=lambda f: normal_channels(f))(frame)
    assert InvariantLoss(target)(frame) == pytest.approx(general, rel=1e-10, abs=1e-13)
    assert PartsInvariantLoss(target)(frame) == pytest.approx(
        InvariantLoss(target, channels=part_channels)(frame), rel=1e-10, abs=1e-13)


def test_compiled_moments_refuse_labels_beyond_the_kinds():
    target = PhotoTarget(np.ones((10, 10, 1)), np.ones((10, 10)), np.ones((10, 10), bool))
    labels = np.full((4, 4), Frame.n_parts + 1, np.uint8)
    with pytest.raises(ValueError, match="kinds"):
        PartsInvariantLoss(target)(Frame(np.ones((4, 4, 4), np.float32), labels, 0, 0, 10, 10))
