"""The overlay: the outline, the material boundaries and the wheels the photo can show."""

from __future__ import annotations

import numpy as np
import pytest

from vehicle_pose.geometry.camera import look_at_camera
from vehicle_pose.render.overlay import _WHEELS, draw_overlay


@pytest.mark.parametrize("azimuth", [40.0, 220.0])
def test_the_wheels_marked_are_those_whose_outer_face_the_camera_sees(sedan, renderer, azimuth):
    """A three-quarter view: the hubs of the near side are marked, the far side's, behind the
    body, are not."""
    centre = sedan.mesh.sphere[0]
    cam = look_at_camera(centre, [1.0, 0.0, 0.0], [0.0, 0.0, 1.0], azimuth_deg=azimuth, elevation_deg=10.0,
                         distance=9.0, focal=700.0, width=640, height=480)
    out = draw_overlay(np.zeros((480, 640, 3), np.uint8), sedan.mesh, cam, renderer=renderer, wheels=sedan.wheels)
    red = np.all(out == _WHEELS, axis=2)
    near, far = [], []
    for side in ("left", "right"):
        g = sedan.wheels.side(side)
        hubs = cam.project(np.stack([g.rear, g.front]))
        (near if float((cam.R @ g.axle)[2]) < 0.0 else far).extend(hubs)
    assert len(near) == 2 and len(far) == 2
    for x, y in near:
        assert red[int(round(y)), int(round(x))]
    for x, y in far:
        assert min(np.hypot(x - a, y - b) for a, b in near) > 20.0  # the two sides apart in the picture
        assert not red[int(round(y)) - 3:int(round(y)) + 4, int(round(x)) - 3:int(round(x)) + 4].any()
