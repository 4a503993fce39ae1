"""The vehicle's region found with no hint."""

from __future__ import annotations

import numpy as np

from vehicle_pose.metrics import iou
from vehicle_pose.render.synth import synthesize
from vehicle_pose.segment.region import VehicleRegion, find_vehicle

from helpers import view


def test_region_from_mask():
    mask = np.zeros((40, 60), bool)
    mask[10:20, 5:30] = True
    region = VehicleRegion.from_mask(mask)
    assert region.box == (5.0, 10.0, 29.0, 19.0) and region.area_fraction == mask.mean()
    assert region.resized(120, 80).box == (10.0, 20.0, 58.0, 38.0)
    assert VehicleRegion.from_mask(np.zeros((4, 4), bool)).mask.all()


def test_vehicle_region_without_hint(library, renderer):
    truth = view(library.load("suv"), 60.0, 12.0, focal=900.0, distance=10.0)
    photo, mask = synthesize(library.load("suv").mesh, truth, renderer=renderer, seed=3)
    region = find_vehicle(photo)
    assert iou(region.mask, mask) > 0.9
    ys, xs = np.nonzero(mask)
    assert np.allclose(region.box, (xs.min(), ys.min(), xs.max(), ys.max()), atol=12)
