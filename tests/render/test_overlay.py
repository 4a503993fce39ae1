"""The overlay: the outline, the material boundaries and the wheels the photo can show."""

from __future__ import annotations

import numpy as np
import pytest

from vehicle_pose.geometry.camera import Camera, look_at_camera
from vehicle_pose.render.overlay import _WHEELS, draw_overlay
from vehicle_pose.render.parts import part_map

from helpers import view


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


def _panel(out: np.ndarray, grey: int) -> tuple[int, int, int, int]:
    """The box (x0, y0, x1, y1) of the legend's dark panel on a photo of one ``grey``."""
    ys, xs = np.nonzero(np.all(out == int(0.35 * grey), axis=2))
    return int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1


@pytest.mark.parametrize(("shift", "corner"), [((0.0, 0.0), (0, 0)), ((-180.0, -120.0), (1, 0))])
def test_the_legend_lies_in_the_corner_where_it_hides_the_least_of_the_model(sedan, renderer, shift, corner):
    """Centred, the car leaves the top left free and the legend is drawn there; moved into the
    top left, the legend goes to the first corner it leaves free (top right) and hides none of it."""
    base = view(sedan, 40.0, 15.0, focal=500.0)
    K = base.K.copy()
    K[0, 2] += shift[0]
    K[1, 2] += shift[1]
    cam = Camera(K, base.R, base.t, base.width, base.height)
    parts = part_map(sedan, cam, renderer)
    covered = renderer.render(sedan.mesh, cam).coverage
    assert covered[:120, :240].any() == (shift != (0.0, 0.0))  # the car reaches the top left when moved
    grey = 200
    out = draw_overlay(np.full((480, 640, 3), grey, np.uint8), sedan.mesh, cam, renderer=renderer, parts=parts)
    x0, y0, x1, y1 = _panel(out, grey)
    assert ((x0 + x1) / 2 > 320, (y0 + y1) / 2 > 240) == (bool(corner[0]), bool(corner[1]))
    assert not covered[y0:y1, x0:x1].any()
