"""Windows of the photo around the vehicle, and their cameras."""

from __future__ import annotations

import numpy as np

from vehicle_pose.geometry.window import Window

from helpers import view


def test_window_grows_the_box_within_the_image_and_never_enlarges():
    w = Window.around((100.0, 200.0, 300.0, 260.0), 640, 480, size=160, margin=0.25)
    assert (w.x0, w.y0, w.x1, w.y1) == (50, 150, 351, 311)  # grown by 0.25 x 200 px
    assert max(w.width, w.height) == 160 and abs(w.width / w.height - 301 / 161) < 0.02
    edge = Window.around((0.0, 0.0, 40.0, 30.0), 640, 480, size=400, margin=0.5)
    assert (edge.x0, edge.y0, edge.x1, edge.y1, edge.width, edge.height) == (0, 0, 61, 51, 61, 51)
    whole = Window.around((100.0, 200.0, 300.0, 260.0), 640, 480, size=160, margin=None)
    assert (whole.x0, whole.y0, whole.x1, whole.y1, whole.width, whole.height) == (0, 0, 640, 480, 160, 120)


def test_window_camera_projects_where_the_crop_shows_the_point(sedan):
    full = view(sedan, 40.0, 10.0)
    w = Window.around((200.0, 150.0, 420.0, 330.0), 640, 480, size=150, margin=0.2)
    s = np.array([w.width / (w.x1 - w.x0), w.height / (w.y1 - w.y0)])  # sizes are rounded per axis
    pts = sedan.mesh.sample_points(200)
    expected = (full.project(pts) - [w.x0, w.y0] + 0.5) * s - 0.5  # pixel centres at integers
    assert np.allclose(w.camera(full).project(pts), expected, atol=1e-6)
    back = w.full_camera(w.camera(full))
    assert (back.width, back.height) == (640, 480)
    assert np.allclose(back.K, full.K) and np.allclose(back.R, full.R) and np.allclose(back.t, full.t)
    # A camera of the photo at another size maps to the same window camera.
    assert np.allclose(w.camera(full.scaled(320, 240)).K, w.camera(full).K)


def test_window_render_is_the_crop_of_the_full_render(sedan, renderer):
    full = view(sedan, 130.0, 15.0)
    coverage = renderer.render(sedan.mesh, full).coverage
    ys, xs = np.nonzero(coverage)
    w = Window.around((xs.min(), ys.min(), xs.max(), ys.max()), 640, 480, size=120, margin=0.1)
    windowed = renderer.render(sedan.mesh, w.camera(full)).coverage
    cropped = w.mask(coverage)
    assert windowed.shape == (w.height, w.width)
    assert (windowed & cropped).sum() / (windowed | cropped).sum() > 0.93
    pasted = w.full_mask(windowed)
    assert pasted.shape == (480, 480 * 4 // 3) and not pasted[:, : w.x0].any() and not pasted[: w.y0].any()
    assert (pasted & coverage).sum() / (pasted | coverage).sum() > 0.9
    image = np.zeros((480, 640, 3), np.uint8)
    image[w.y0 : w.y1, w.x0 : w.x1] = 200
    assert w.image(image).shape == (w.height, w.width, 3) and (w.image(image) == 200).all()
