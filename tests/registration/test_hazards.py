"""Synthetic photos with one of real photos' difficulties each, registered within a few pixels."""

from __future__ import annotations

import numpy as np
import pytest

from vehicle_pose import register
from vehicle_pose.geometry.camera import Camera
from vehicle_pose.render.synth import HAZARDS, border_crop_camera, synthesize_hazard

from helpers import perturbed, projection_error, view

pytestmark = pytest.mark.slow


def _box(mask: np.ndarray) -> tuple[float, float, float, float]:
    ys, xs = np.nonzero(mask)
    return float(xs.min()), float(ys.min()), float(xs.max() + 1), float(ys.max() + 1)


def _truth(sedan, hazard: str, azimuth: float) -> Camera:
    cam = view(sedan, azimuth, 14.0, width=320, height=240, focal=450.0)
    if hazard == "mirror-floor":
        # The car in the upper part of the photo, its mirror image below it.
        K = cam.K.copy()
        K[1, 2] -= 45.0
        cam = Camera(K, cam.R, cam.t, cam.width, cam.height)
    return cam


@pytest.mark.parametrize("hazard,azimuth,seed", [
    ("mirror-floor", 40.0, 0), ("sky-on-glass", 95.0, 1), ("second-car", 140.0, 2),
    ("border-crop", 230.0, 3), ("specular", 300.0, 4), ("mirror-paint", 20.0, 5),
])
def test_registered_within_a_few_pixels(sedan, renderer, hazard, azimuth, seed):
    assert hazard in HAZARDS
    photo, mask, truth = synthesize_hazard(sedan.mesh, _truth(sedan, hazard, azimuth), hazard, renderer=renderer,
                                           seed=seed)
    start = perturbed(truth, seed, degrees=8.0)
    assert projection_error(sedan, start, truth) > 6.0
    result = register(photo, sedan, init_camera=start, bbox=_box(mask), renderer=renderer)
    assert projection_error(sedan, result.camera, truth) < 1.5


def test_border_crop_cuts_the_wanted_share(sedan, renderer):
    cam = view(sedan, 60.0, 14.0, width=320, height=240, focal=450.0)
    cropped = border_crop_camera(sedan.mesh, cam)
    uv = cropped.project(sedan.mesh.vertices)
    width = uv[:, 0].max() - uv[:, 0].min()
    assert (uv[:, 0].max() - (cropped.width - 1)) / width == pytest.approx(0.15, abs=1e-6)
    _, mask, truth = synthesize_hazard(sedan.mesh, cam, "border-crop", renderer=renderer)
    assert truth is not cam and mask[:, -1].any()


def test_an_unknown_hazard_is_refused(sedan, renderer):
    with pytest.raises(ValueError, match="unknown hazard"):
        synthesize_hazard(sedan.mesh, view(sedan, 0.0, 10.0), "fog", renderer=renderer)
