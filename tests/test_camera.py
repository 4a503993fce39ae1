"""Cameras read from JSON: what a client may send and what it is refused."""

from __future__ import annotations

import json

import pytest

from vehicle_pose.camera import MAX_MAGNITUDE, Camera
from vehicle_pose.errors import CameraError

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
])
def test_numbers_no_projection_can_use_are_camera_errors(change, message):
    with pytest.raises(CameraError, match=message):
        Camera.from_dict({**BASE, **change})


@pytest.mark.parametrize("text", ['{"width": ' + "9" * 5000 + "}", "[" * 100_000 + "]" * 100_000])
def test_a_camera_file_that_json_cannot_hold_is_a_camera_error(tmp_path, text):
    path = tmp_path / "cam.json"
    path.write_text(text)
    with pytest.raises(CameraError, match="cannot be read"):
        Camera.load(path)
