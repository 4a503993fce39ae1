"""Start poses: the view search, distinct candidates, and the start fitted to the client's box."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vehicle_pose.geometry.camera import Camera
from vehicle_pose.metrics import rotation_error
from vehicle_pose.render.synth import LIGHTINGS, border_crop_camera, synthesize
from vehicle_pose.search.views import (
    box_overflow,
    distinct,
    fit_to_box,
    turned_away,
    view_search,
)
from vehicle_pose.segment.region import find_vehicle

from helpers import view


def _projected_box(camera: Camera, points: np.ndarray, clip: bool = False) -> np.ndarray:
    uv = camera.project(points)
    lo, hi = uv.min(0), uv.max(0)
    if clip:
        size = np.array([camera.width - 1.0, camera.height - 1.0])
        lo, hi = np.clip(lo, 0, size), np.clip(hi, 0, size)
    return np.concatenate([lo, hi])


def _moved(camera: Camera, shift: np.ndarray) -> Camera:
    return Camera(camera.K, camera.R, camera.t + shift, camera.width, camera.height)


def test_fit_to_box_recovers_place_and_size_and_keeps_rotation(sedan):
    truth = view(sedan, 70.0, 12.0, width=640, height=480, focal=900.0)
    points = sedan.mesh.sample_points(600)
    box = tuple(_projected_box(truth, points))
    start = _moved(truth, np.array([0.6, -0.3, 2.5]))  # off to one side and too small
    fitted = fit_to_box(start, points, sedan.mesh.sphere[0], box, rounds=5)
    assert np.abs(_projected_box(fitted, points) - box).max() < 2.0
    assert rotation_error(fitted.R, truth.R) < 1e-9 and np.allclose(fitted.K, truth.K)


def test_a_box_cut_by_the_border_is_matched_by_a_projection_cut_the_same_way(sedan):
    truth = border_crop_camera(sedan.mesh, view(sedan, 70.0, 12.0, width=640, height=480, focal=900.0), 0.3)
    points = sedan.mesh.sample_points(600)
    box = tuple(_projected_box(truth, points, clip=True))
    assert box[2] == pytest.approx(639.0)
    start = _moved(truth, np.array([-0.4, 0.2, 1.5]))
    clipped = fit_to_box(start, points, sedan.mesh.sphere[0], box, rounds=5, clip=True)
    plain = fit_to_box(start, points, sedan.mesh.sphere[0], box, rounds=5)
    # The plain fit shrinks the whole vehicle into the box; the clipped one lets it run on
    # beyond the border, as in the photo.
    assert np.abs(_projected_box(clipped, points, clip=True) - box).max() < 0.03 * (box[2] - box[0])
    size = lambda cam: np.ptp(cam.project(points)[:, 0])  # noqa: E731
    assert size(clipped) == pytest.approx(size(truth), rel=0.03)
    assert size(plain) < 0.85 * size(truth)


def test_box_overflow_counts_only_what_leaves_the_grown_box(sedan):
    cam = view(sedan, 30.0, 12.0, width=640, height=480, focal=900.0)
    points = sedan.mesh.sample_points(600)
    x0, y0, x1, y1 = _projected_box(cam, points)
    w = x1 - x0
    assert box_overflow(cam, points, (x0, y0, x1, y1), 0.0) == pytest.approx(0.0, abs=1e-9)
    # A box 10 % narrower on the right: 10 % of its width out, free within a 20 % tolerance.
    narrow = (x0, y0, x1 - 0.1 * w, y1)
    assert box_overflow(cam, points, narrow, 0.0) == pytest.approx(0.1 / 0.9, rel=1e-6)
    assert box_overflow(cam, points, narrow, 0.2) == 0.0
    # A larger box costs nothing: falling short of the box is not counted.
    assert box_overflow(cam, points, (x0 - 50, y0 - 50, x1 + 50, y1 + 50), 0.0) == 0.0


def test_box_overflow_leaves_sides_on_the_photo_border_free(sedan):
    cam = border_crop_camera(sedan.mesh, view(sedan, 30.0, 12.0, width=640, height=480, focal=900.0), 0.3)
    points = sedan.mesh.sample_points(600)
    x0, y0, _, y1 = _projected_box(cam, points)
    assert box_overflow(cam, points, (x0, y0, 639.0, y1), 0.0) == pytest.approx(0.0, abs=1e-9)
    assert box_overflow(cam, points, (x0, y0, 600.0, y1), 0.0) > 0.1
    behind = Camera(cam.K, cam.R, cam.t - np.array([0.0, 0.0, 100.0]), cam.width, cam.height)
    assert box_overflow(behind, points, (x0, y0, 639.0, y1), 0.0) == 4.0


def test_box_shortfall_counts_a_projection_shrunk_inside_the_box(sedan):
    cam = view(sedan, 30.0, 12.0, width=640, height=480, focal=900.0)
    points = sedan.mesh.sample_points(600)
    x0, y0, x1, y1 = _projected_box(cam, points)
    w, h = x1 - x0, y1 - y0
    loose = (x0 - 0.1 * w, y0, x1, y1)  # 10 % loose on the left: within a 15 % shortfall
    assert box_overflow(cam, points, loose, 0.0, 0.15) == pytest.approx(0.0, abs=1e-9)
    # A box twice as tall (the model covers only its upper half): the bottom falls short by
    # half the box's height less the tolerance.
    tall = (x0, y0, x1, y1 + h)
    assert box_overflow(cam, points, tall, 0.0, 0.15) == pytest.approx(0.5 - 0.15, rel=1e-6)
    assert box_overflow(cam, points, tall, 0.0) == pytest.approx(0.0, abs=1e-9)


def test_turned_away_is_the_squared_angle_from_the_start_in_units_of_the_spread(sedan):
    start = view(sedan, 30.0, 12.0, width=640, height=480, focal=900.0)
    assert turned_away(start, start, 10.0) == pytest.approx(0.0, abs=1e-6)
    for axis in ([0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.3, 0.4, 0.866]):
        r = np.radians(20.0) * np.asarray(axis) / np.linalg.norm(axis)
        turned = Camera(start.K, cv2.Rodrigues(r)[0] @ start.R, start.t + 1.0, start.width, start.height)
        # Only the rotation counts: 20 degrees is twice a spread of 10, whatever the place.
        assert turned_away(turned, start, 10.0) == pytest.approx(4.0, rel=1e-6)
        assert turned_away(turned, start, 20.0) == pytest.approx(1.0, rel=1e-6)


@pytest.mark.parametrize(
    "model_id,azimuth,elevation",
    [("sedan", 35.0, 12.0), ("hatchback", 140.0, 20.0), ("van", 200.0, 8.0), ("pickup", 300.0, 25.0),
     ("suv", 0.0, 15.0)],
)
def test_view_search_returns_a_candidate_within_20_degrees(library, renderer, model_id, azimuth, elevation):
    model = library.load(model_id)
    truth = view(model, azimuth, elevation, focal=900.0, distance=10.0)
    photo, _ = synthesize(model.mesh, truth, lighting=LIGHTINGS["side"], renderer=renderer, seed=7)
    cands = distinct(view_search(photo, find_vehicle(photo), model, renderer), 4)
    assert min(rotation_error(c.camera.R, truth.R) for c in cands) < 20.0
