"""The loss weights of the pixels GrabCut calls background inside the client's box."""

from __future__ import annotations

import numpy as np
import pytest

from vehicle_pose import RegistrationOptions
from vehicle_pose.loss.invariant import InvariantLoss, invariant_loss, make_target
from vehicle_pose.registration.segmentation import box_mask, doubt_weights
from vehicle_pose.render.renderer import Frame


def _scene() -> tuple[np.ndarray, np.ndarray]:
    fg = np.zeros((40, 60), bool)
    fg[10:25, 15:45] = True  # GrabCut's vehicle: the box's lower rows left out
    region = box_mask((15, 10, 45, 32), 60, 40, 0.0)
    return fg, region


def test_only_the_box_pixels_left_out_by_grabcut_are_doubted():
    fg, region = _scene()
    w = doubt_weights(fg, region, 0.3)
    assert w is not None and w.shape == fg.shape
    doubtful = region & ~fg
    assert doubtful.sum() > 0
    assert np.all(w[doubtful] == 0.3)
    assert np.all(w[~doubtful] == 1.0)


def test_the_region_is_resized_to_the_level():
    fg, region = _scene()
    small = fg[::2, ::2]
    w = doubt_weights(small, region, 0.0)
    assert w is not None and w.shape == small.shape
    assert w[14, 15] == 0.0 and w[2, 2] == 1.0 and w[8, 15] == 1.0


def test_no_box_or_full_weight_means_unit_weights():
    fg, region = _scene()
    assert doubt_weights(fg, None, 0.3) is None
    assert doubt_weights(fg, region, 1.0) is None
    assert doubt_weights(region, region, 0.3) is None  # nothing left out
    assert RegistrationOptions().segmentation.doubt_weight == 1.0
    with pytest.raises(ValueError, match="doubt_weight"):
        RegistrationOptions.from_flat({"doubt_weight": 1.5})


def test_a_doubted_pixel_at_weight_zero_does_not_count():
    """At weight 0 the loss is the loss of the other pixels alone, whatever the model does there."""
    rng = np.random.default_rng(3)
    fg, region = _scene()
    rgb = rng.integers(0, 256, size=(40, 60, 3), dtype=np.uint8)
    w = doubt_weights(fg, region, 0.0)
    assert w is not None
    target = make_target(rgb, fg, color=False, weights=w)
    attrs = np.zeros((40, 60, 4), np.float32)
    attrs[8:35, 12:48] = rng.normal(size=(27, 36, 4))
    frame = Frame(attrs, (np.abs(attrs).sum(-1) > 0).astype(np.uint8), 0, 0, 60, 40)
    kept = (w > 0).reshape(-1)
    full = np.concatenate([(np.abs(attrs).sum(-1) > 0)[..., None], attrs], -1).reshape(-1, 5)
    direct = invariant_loss(target.image.reshape(-1, 1)[kept], full[kept])
    assert InvariantLoss(target)(frame) == pytest.approx(direct, rel=1e-9)
