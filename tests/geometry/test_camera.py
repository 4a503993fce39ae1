"""The OpenCV camera: round trips, refused numbers and files, photos of another shape."""

from __future__ import annotations

import json

import numpy as np
import pytest

from vehicle_pose.errors import CameraError
from vehicle_pose.geometry.camera import MAX_MAGNITUDE, Camera

BASE = {"K": [[500, 0, 160], [0, 500, 120], [0, 0, 1]], "R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "t": [0, 0, 5],
        "width": 320, "height": 240}


def test_a_plain_camera_round_trips():
    cam = Camera.from_dict(json.loads(json.dumps(BASE)))
    assert Camera.from_dict(cam.to_dict()).to_dict() == cam.to_dict()


@pytest.mark.parametrize("change,message", [
    ({"width": float("inf")}, "out-of-range"),
    ({"height": 10**400}, "outside 1-"),
    ({"width": 0}, "outside 1-"),
    ({"K": [[10**400, 0, 160], [0, 500, 120], [0, 0, 1]]}, "out-of-range"),
    ({"t": [0, 0, 1e300]}, "beyond"),
    ({"K": [[2 * MAX_MAGNITUDE, 0, 160], [0, 500, 120], [0, 0, 1]]}, "beyond"),
    ({"t": [0, float("nan"), 5]}, "non-finite"),
    ({"t": ["a", 0, 5]}, "non-numeric"),
    ({"K": [[500, 0, 160], [5, 500, 120], [0, 0, 1]]}, r"\[0, fy, cy\]"),
    ({"K": [[500, 0, 160], [0, 500, 120], [0, 0, 2]]}, r"\[0, 0, 1\]"),
])
def test_numbers_no_projection_can_use_are_camera_errors(change, message):
    with pytest.raises(CameraError, match=message):
        Camera.from_dict({**BASE, **change})


@pytest.mark.parametrize("text,message", [('{"width": ' + "9" * 5000 + "}", "limit .* digits"),
                                          ("[" * 100_000 + "]" * 100_000, "nested too deeply"),
                                          ('{"K": ', "not valid JSON")])
def test_a_camera_file_that_json_cannot_hold_is_a_camera_error_that_says_why(tmp_path, text, message):
    path = tmp_path / "cam.json"
    path.write_text(text)
    with pytest.raises(CameraError, match=message):
        Camera.load(path)
    with pytest.raises(CameraError, match="init_camera .*" + message):
        Camera.from_json(text, what="init_camera")


def test_a_camera_for_another_aspect_ratio_is_refused_not_stretched():
    cam = Camera(np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]]), np.eye(3), np.array([0, 0, 10.0]), 640,
                 480)
    assert cam.for_photo(640, 480) is cam
    half = cam.for_photo(320, 240)
    assert half.K[0, 0] == pytest.approx(250.0) and half.K[1, 1] == pytest.approx(250.0)
    cam.for_photo(1000, 751)  # rounding of a resize: within 1 %
    with pytest.raises(CameraError, match="aspect ratio"):
        cam.for_photo(480, 640)  # the photo turned by its EXIF orientation
    with pytest.raises(CameraError, match="640x480"):
        cam.for_photo(640, 360)
