"""GrabCut seeded by a start pose, and the client's box."""

from __future__ import annotations

import numpy as np
import pytest

from vehicle_pose.geometry.camera import Camera
from vehicle_pose.metrics import iou
from vehicle_pose.registration.segmentation import box_mask
from vehicle_pose.render.synth import synthesize
from vehicle_pose.segment.grabcut import grabcut_foreground

from helpers import view


@pytest.fixture(scope="module")
def scene(sedan, renderer):
    truth = view(sedan, 60.0, 15.0)
    photo, mask = synthesize(sedan.mesh, truth, renderer=renderer, seed=5)
    # A start pose whose silhouette sits a fifth of the vehicle's height too high.
    ys, xs = np.nonzero(mask)
    K = truth.K.copy()
    K[1, 2] -= 0.2 * (ys.max() - ys.min())
    shifted = Camera(K, truth.R, truth.t, truth.width, truth.height)
    start = renderer.render(sedan.mesh, shifted).coverage
    box = (xs.min() - 3.0, ys.min() - 3.0, xs.max() + 3.0, ys.max() + 3.0)
    return photo, mask, start, box


def test_a_start_pose_off_the_vehicle_loses_what_its_grown_silhouette_misses(scene):
    photo, mask, start, _ = scene
    fg = grabcut_foreground(photo, start, margin=0.06)
    assert (mask & ~fg).sum() > 0.05 * mask.sum()


def test_the_clients_box_lets_grabcut_claim_the_rest_of_the_vehicle(scene):
    photo, mask, start, box = scene
    H, W = mask.shape
    without = grabcut_foreground(photo, start, margin=0.06)
    with_box = grabcut_foreground(photo, start, margin=0.06, region=box_mask(box, W, H, 0.04))
    assert (mask & ~with_box).sum() < 0.02 * mask.sum()
    assert iou(with_box, mask) > 0.95 > iou(without, mask)
