"""The paper's pose parameters theta and their exact camera: round trips and domains."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vehicle_pose.errors import PoseError
from vehicle_pose.geometry.camera import Camera
from vehicle_pose.geometry.pose import Theta, camera_to_theta, theta_to_camera, visible_side
from vehicle_pose.model.metadata import WheelGeometry

WHEELS = WheelGeometry(np.array([-1.3, 0.02, 0.31]), np.array([1.4, 0.02, 0.31]), np.array([0.0, 1.0, 0.0]), 1.56, 0.31)


W, H = 640, 480


@st.composite
def thetas(draw):
    side = draw(st.sampled_from(["left", "right"]))
    mu = np.array([draw(st.floats(100, 540)), draw(st.floats(100, 380))])
    ang = draw(st.floats(0, 2 * np.pi))
    length = draw(st.floats(60, 400))
    delta = length * np.array([np.cos(ang), np.sin(ang)])
    r = draw(st.floats(0.0, 0.9))
    phi = draw(st.floats(0, 2 * np.pi))
    psi = np.array([r * np.cos(phi), r * np.sin(phi), -np.sqrt(1 - r * r)])
    f = draw(st.floats(300, 20000))
    return Theta(mu, delta, psi, f, side)


def _valid_camera(theta: Theta) -> Camera | None:
    try:
        return theta_to_camera(theta, WHEELS.side(theta.side), W, H)
    except PoseError:
        return None


@settings(max_examples=200, deadline=None)
@given(theta=thetas())
def test_theta_camera_theta_round_trip(theta):
    cam = _valid_camera(theta)
    if cam is None:
        return
    back = camera_to_theta(cam, WHEELS.side(theta.side), theta.side)
    np.testing.assert_allclose(back.vector(), theta.vector(), rtol=1e-9, atol=1e-9 * max(1.0, theta.f))


@settings(max_examples=200, deadline=None)
@given(theta=thetas())
def test_wheel_centres_land_on_mu_and_mu_plus_delta(theta):
    cam = _valid_camera(theta)
    if cam is None:
        return
    g = WHEELS.side(theta.side)
    uv = cam.project(np.stack([g.rear, g.front]))
    np.testing.assert_allclose(uv[0], theta.mu, atol=1e-9 * max(1.0, np.abs(theta.mu).max()))
    np.testing.assert_allclose(uv[1], theta.mu + theta.delta, atol=1e-8)
    assert np.allclose(cam.R @ g.axle, theta.psi / np.linalg.norm(theta.psi), atol=1e-12)
    assert np.linalg.det(cam.R) == pytest.approx(1.0)


@settings(max_examples=100, deadline=None)
@given(theta=thetas())
def test_camera_theta_camera_round_trip(theta):
    cam = _valid_camera(theta)
    if cam is None:
        return
    side = visible_side(cam, WHEELS.side("left"))
    assert side == theta.side
    again = theta_to_camera(camera_to_theta(cam, WHEELS.side(side), side), WHEELS.side(side), W, H)
    np.testing.assert_allclose(again.R, cam.R, atol=1e-9)
    np.testing.assert_allclose(again.t, cam.t, rtol=1e-9, atol=1e-9 * np.abs(cam.t).max())
    np.testing.assert_allclose(again.K, cam.K, rtol=1e-12)


def test_normalised_vector_round_trip():
    theta = Theta(np.array([200.0, 300.0]), np.array([-250.0, 12.0]), np.array([0.3, 0.1, -np.sqrt(0.9)]), 1500.0,
                  "left")
    x = theta.normalized(W, H)
    back = Theta.from_normalized(x, W, H, "left")
    np.testing.assert_allclose(back.vector(), theta.vector(), rtol=1e-12)
    assert x[6] == pytest.approx(10 * W / 1500.0)


def test_out_of_domain_theta_is_refused():
    with pytest.raises(PoseError):
        Theta.from_normalized([0.5, 0.5, 0.3, 0.0, 0.9, 0.9, 1.0], W, H, "left")
    with pytest.raises(PoseError):
        theta_to_camera(Theta(np.array([1.0, 1.0]), np.zeros(2), np.array([0, 0, -1.0]), 800.0, "left"),
                        WHEELS.side("left"), W, H)
