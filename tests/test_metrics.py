"""Pose error metrics: one definition each, checked on poses made by the project's own code."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vehicle_pose.geometry.camera import Camera
from vehicle_pose.metrics import iou, projection_error, rotation_error


def _camera(R: np.ndarray, t: tuple[float, float, float], width: int = 640) -> Camera:
    K = np.array([[800.0, 0.0, width / 2 - 0.5], [0.0, 800.0, 239.5], [0.0, 0.0, 1.0]])
    return Camera(K, R, np.array(t), width, 480)


@pytest.mark.parametrize("degrees", [0.0, 1.0, 30.0, 179.0])
def test_rotation_error_is_the_angle_between_rotations(degrees: float) -> None:
    base = Rotation.from_rotvec([0.3, -0.2, 0.1]).as_matrix()
    turned = Rotation.from_rotvec(np.radians(degrees) * np.array([0.0, 0.6, 0.8])).as_matrix() @ base
    assert rotation_error(turned, base) == pytest.approx(degrees, abs=1e-5)
    assert rotation_error(base, turned) == pytest.approx(degrees, abs=1e-5)


def test_projection_error_is_the_mean_pixel_distance_and_scales_to_a_width() -> None:
    points = np.random.default_rng(0).uniform(-1, 1, size=(50, 3))
    truth = _camera(np.eye(3), (0.0, 0.0, 10.0))
    shifted = _camera(np.eye(3), (0.01, 0.0, 10.0))
    d = np.linalg.norm(shifted.project(points) - truth.project(points), axis=1).mean()
    assert projection_error(points, shifted, truth) == pytest.approx(d)
    assert projection_error(points, truth, truth) == 0.0
    wide, wide_truth = _camera(np.eye(3), (0.01, 0.0, 10.0), 1280), _camera(np.eye(3), (0.0, 0.0, 10.0), 1280)
    raw = projection_error(points, wide, wide_truth)
    assert projection_error(points, wide, wide_truth, width=640) == pytest.approx(raw / 2)


def test_a_point_behind_a_camera_makes_the_error_infinite() -> None:
    points = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -20.0]])
    truth = _camera(np.eye(3), (0.0, 0.0, 10.0))
    assert projection_error(points, truth, truth) == float("inf")


def test_iou_of_masks() -> None:
    a = np.zeros((4, 4), bool)
    b = np.zeros((4, 4), bool)
    assert iou(a, b) == 0.0
    a[:2] = True
    b[1:3] = True
    assert iou(a, b) == pytest.approx(4 / 12)
    assert iou(a, a) == 1.0
