"""The search coordinates: the view perturbation, its pivoted dolly zoom, the paper's theta."""

from __future__ import annotations

import numpy as np
import pytest

from vehicle_pose.geometry.parametrize import ThetaParams, ViewParams

from helpers import view


def test_view_origin_is_the_reference(sedan):
    ref = view(sedan, 0.0, 15.0)
    params = ViewParams(ref, sedan.mesh.sphere[0])
    cam = params.camera(params.start())
    np.testing.assert_allclose(cam.R, ref.R, atol=1e-12)
    np.testing.assert_allclose(cam.t, ref.t, atol=1e-9)
    np.testing.assert_allclose(cam.K, ref.K, atol=1e-9)


def test_view_focal_change_keeps_the_centre_and_scale(sedan):
    ref = view(sedan, 30.0, 15.0)
    centre = sedan.mesh.sphere[0]
    params = ViewParams(ref, centre)
    zoomed = params.camera(np.array([0, 0, 0, 0, 0, 0, np.log(2.0)]))
    assert zoomed.focal == pytest.approx(2 * ref.focal)
    np.testing.assert_allclose(zoomed.project(centre[None]), ref.project(centre[None]), atol=1e-9)
    assert zoomed.to_camera(centre[None])[0, 2] == pytest.approx(2 * ref.to_camera(centre[None])[0, 2])


@pytest.mark.parametrize("pivot", [0.5, 1.2])
def test_view_focal_change_with_a_pivot_keeps_the_size_there(sedan, pivot):
    ref = view(sedan, 30.0, 15.0)
    centre, radius = sedan.mesh.sphere
    params = ViewParams(ref, centre, pivot * radius)
    np.testing.assert_allclose(params.camera(params.start()).t, ref.t, atol=1e-9)
    depth = ref.to_camera(centre[None])[0, 2]
    zoomed = params.camera(np.array([0, 0, 0, 0, 0, 0, np.log(0.6)]))
    np.testing.assert_allclose(zoomed.project(centre[None]), ref.project(centre[None]), atol=1e-9)
    # The image scale f / depth is unchanged pivot * radius in front of the centre...
    new_depth = zoomed.to_camera(centre[None])[0, 2]
    assert zoomed.focal / (new_depth - pivot * radius) == pytest.approx(ref.focal / (depth - pivot * radius))
    # ...and the log scale coordinate scales it there.
    grown = params.camera(np.array([0, 0, 0, 0, 0, np.log(1.25), 0]))
    grown_depth = grown.to_camera(centre[None])[0, 2]
    assert ref.focal / (grown_depth - pivot * radius) == pytest.approx(1.25 * ref.focal / (depth - pivot * radius))


def test_view_pivot_stays_in_front_of_the_camera(sedan):
    """A pivot further than half the centre's depth is held there: the camera never reaches it."""
    ref = view(sedan, 30.0, 15.0)
    centre, radius = sedan.mesh.sphere
    depth = ref.to_camera(centre[None])[0, 2]
    params = ViewParams(ref, centre, 10.0 * depth)
    for g in (-6.0, 0.0, 3.0):
        cam = params.camera(np.array([0, 0, 0, 0, 0, 0, g]))
        assert cam.to_camera(centre[None])[0, 2] > 0.5 * depth


def test_theta_origin_is_the_reference(sedan):
    ref = view(sedan, 100.0, 15.0)
    params = ThetaParams(ref, sedan.wheels.side("left"), "left")
    cam = params.camera(params.start())
    np.testing.assert_allclose(cam.R, ref.R, atol=1e-9)
    np.testing.assert_allclose(cam.t, ref.t, atol=1e-8)


pytestmark = pytest.mark.slow


def test_dolly_zooms_keep_centre_size_and_orientation(sedan):
    cam = view(sedan, 40.0, 15.0, focal=900.0)
    centre = sedan.mesh.sphere[0]
    for factor in (0.6, 1.7):
        zoomed = ViewParams(cam, centre).dolly_zoom(factor)
        assert zoomed.focal == pytest.approx(factor * cam.focal)
        np.testing.assert_allclose(zoomed.R, cam.R, atol=1e-12)
        np.testing.assert_allclose(zoomed.project(centre[None]), cam.project(centre[None]), atol=1e-6)
        # The apparent size at the centre's depth is kept: f / depth is unchanged.
        depth, depth0 = zoomed.to_camera(centre[None])[0, 2], cam.to_camera(centre[None])[0, 2]
        assert zoomed.focal / depth == pytest.approx(cam.focal / depth0)


@pytest.mark.parametrize("g", [-1.0, -0.05, 0.0, 0.04, 0.7])
def test_a_focal_band_holds_the_focal_length_and_moves_the_depth_with_it(sedan, g):
    ref = view(sedan, 30.0, 15.0)
    centre, radius = sedan.mesh.sphere
    band = (ref.focal / ref.width / 1.1, ref.focal / ref.width * 1.1)
    banded = ViewParams(ref, centre, 0.5 * radius, band)
    free = ViewParams(ref, centre, 0.5 * radius)
    x = np.array([0.01, -0.02, 0.0, 0.01, 0.0, 0.02, g])
    cam = banded.camera(x)
    assert band[0] * ref.width - 1e-9 <= cam.focal <= band[1] * ref.width + 1e-9
    # Beyond the band the camera is the band's edge: a dolly zoom there, not a change of size.
    clipped = np.clip(g, -np.log(1.1), np.log(1.1))
    np.testing.assert_allclose(cam.t, free.camera(np.r_[x[:6], clipped]).t, atol=1e-9)


def test_a_focal_band_holds_the_theta_focal_length(sedan):
    ref = view(sedan, 30.0, 15.0)
    band = (1.0, 1.2)
    params = ThetaParams(ref, sedan.wheels.side("left"), "left", band)
    for f_widths in (0.3, 1.1, 5.0):
        x = params.start()
        x[6] = 10.0 / f_widths
        assert band[0] * ref.width - 1e-6 <= params.camera(x).focal <= band[1] * ref.width + 1e-6
