"""End to end on synthetic ground truth: render at a known pose, perturb, recover."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vehicle_pose import RegistrationOptions, register
from vehicle_pose.errors import BlankPhotoError, CameraError, PoseError
from vehicle_pose.geometry.camera import Camera
from vehicle_pose.geometry.parametrize import ViewParams
from vehicle_pose.registration.fit import probe_factors
from vehicle_pose.render.synth import LIGHTINGS, synthesize

from conftest import projection_error, view

pytestmark = pytest.mark.slow


def perturbed(truth: Camera, seed: int, *, degrees: float = 6.0, shift: float = 0.03, focal: float = 0.1) -> Camera:
    """A rough start: rotated by ``degrees``, moved by ``shift`` of the distance, focal off."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    rot = Rotation.from_rotvec(np.radians(degrees) * axis / np.linalg.norm(axis)).as_matrix()
    t = truth.t + shift * np.linalg.norm(truth.t) * rng.normal(size=3) / np.sqrt(3)
    K = truth.K.copy()
    K[0, 0] *= 1 + focal
    K[1, 1] *= 1 + focal
    return Camera(K, rot @ truth.R, t, truth.width, truth.height)


CASES = [("front", 130.0, 15.0, 0), ("side", 70.0, 20.0, 1), ("top", 220.0, 25.0, 2), ("negative", 300.0, 12.0, 3)]


@pytest.mark.parametrize("lighting,azimuth,elevation,seed", CASES)
def test_recovers_pose_below_one_pixel(sedan, renderer, lighting, azimuth, elevation, seed):
    truth = view(sedan, azimuth, elevation, focal=1000.0)
    photo, _ = synthesize(sedan.mesh, truth, lighting=LIGHTINGS[lighting], renderer=renderer, seed=seed)
    start = perturbed(truth, seed)
    assert projection_error(sedan, start, truth) > 5.0
    result = register(photo, sedan, init_camera=start, renderer=renderer)
    assert projection_error(sedan, result.camera, truth) < 1.0
    assert result.start_source == "init_camera"
    assert result.evaluations > 20 and result.loss < 0.1


def test_coarse_to_fine_is_at_least_as_accurate_as_one_level(sedan, renderer):
    truth = view(sedan, 40.0, 18.0, focal=900.0)
    photo, _ = synthesize(sedan.mesh, truth, lighting=LIGHTINGS["front"], renderer=renderer, seed=11)
    start = perturbed(truth, 11)
    pyramid = register(photo, sedan, init_camera=start, renderer=renderer)
    single = register(photo, sedan, init_camera=start, renderer=renderer,
                      options=RegistrationOptions.from_flat(coarse_to_fine=False))
    assert len(pyramid.levels) == 3 and len(single.levels) == 1
    err_pyramid = projection_error(sedan, pyramid.camera, truth)
    assert err_pyramid < 1.0
    assert err_pyramid <= projection_error(sedan, single.camera, truth) + 0.25


def test_result_json_fields(sedan, renderer):
    truth = view(sedan, 120.0, 15.0, width=320, height=240, focal=450.0)
    photo, _ = synthesize(sedan.mesh, truth, renderer=renderer)
    result = register(photo, sedan, init_camera=perturbed(truth, 2, degrees=3.0), renderer=renderer,
                      options=RegistrationOptions.from_flat(max_evaluations=60))
    d = result.to_dict()
    for key in ("camera", "theta", "loss", "evaluations", "restarts", "seconds", "model", "cam_R_m2c", "cam_t_m2c",
                "cam_K", "start"):
        assert key in d
    assert d["camera"]["width"] == 320 and len(d["cam_R_m2c"]) == 9 and len(d["cam_K"]) == 9
    cam = Camera.from_dict(d["camera"])
    np.testing.assert_allclose(cam.R.reshape(-1), d["cam_R_m2c"])
    assert d["theta"]["side"] in ("left", "right") and d["start"]["source"] == "init_camera"


def test_start_camera_for_another_photo_size_is_rescaled(sedan, renderer):
    truth = view(sedan, 110.0, 15.0, focal=1000.0)
    photo, _ = synthesize(sedan.mesh, truth, renderer=renderer, seed=4)
    start = perturbed(truth, 4, degrees=3.0).scaled(320, 240)
    result = register(photo, sedan, init_camera=start, renderer=renderer)
    assert projection_error(sedan, result.camera, truth) < 1.0


def test_box_only_start_runs_and_says_so(sedan, renderer):
    truth = view(sedan, 90.0, 10.0, focal=1400.0)
    photo, mask = synthesize(sedan.mesh, truth, renderer=renderer, seed=5)
    ys, xs = np.nonzero(mask)
    result = register(photo, sedan, bbox=[xs.min(), ys.min(), xs.max(), ys.max()], renderer=renderer,
                      options=RegistrationOptions.from_flat(max_evaluations=150))
    assert result.start_source == "bbox"
    assert result.evaluations > 0 and np.isfinite(result.loss)


def test_bad_hints_are_clear_errors(sedan, renderer):
    truth = view(sedan, 90.0, 10.0)
    photo, _ = synthesize(sedan.mesh, truth, renderer=renderer)
    away = Camera(truth.K, truth.R, truth.t + np.array([500.0, 0.0, 0.0]), 640, 480)
    with pytest.raises(PoseError, match="off-screen"):
        register(photo, sedan, init_camera=away, renderer=renderer)
    behind = Camera(truth.K, truth.R, -truth.t, 640, 480)
    with pytest.raises(PoseError):
        register(photo, sedan, init_camera=behind, renderer=renderer)
    with pytest.raises(CameraError):
        register(photo, sedan, bbox="1,2,3", renderer=renderer)
    with pytest.raises(ValueError, match="unknown loss"):
        register(photo, sedan, init_camera=truth, options=RegistrationOptions(loss="nope"), renderer=renderer)
    with pytest.raises(CameraError, match="aspect ratio"):
        register(photo[:, :360], sedan, init_camera=truth, renderer=renderer)
    noisy = np.full_like(photo, 128) + (np.arange(photo.size) % 3).reshape(photo.shape).astype(np.uint8)
    for flat in (np.zeros_like(photo), noisy, np.broadcast_to(np.array([90, 100, 110], np.uint8), photo.shape).copy()):
        with pytest.raises(BlankPhotoError, match="nothing to register"):
            register(flat, sedan, init_camera=truth, renderer=renderer)


@pytest.mark.parametrize(
    "loss", ["invariant-paper", "correlation", "squared", "silhouette-iou", "mutual-information", "invariant-parts"])
def test_alternative_losses_run_through_the_same_pipeline(sedan, renderer, loss):
    truth = view(sedan, 60.0, 15.0, width=320, height=240, focal=450.0)
    photo, _ = synthesize(sedan.mesh, truth, renderer=renderer, seed=6)
    start = perturbed(truth, 6, degrees=2.0, shift=0.01, focal=0.03)
    result = register(photo, sedan, init_camera=start, renderer=renderer,
                      options=RegistrationOptions.from_flat(loss=loss, max_evaluations=80))
    assert result.options.loss == loss
    assert projection_error(sedan, result.camera, truth) < projection_error(sedan, start, truth) + 2.0


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


def test_a_start_with_the_wrong_perspective_is_recovered(sedan, renderer):
    """A wide-angle photo registered from a start with 1.8 times its focal length."""
    truth = view(sedan, 35.0, 12.0, distance=5.5, focal=420.0)
    photo, _ = synthesize(sedan.mesh, truth, lighting=LIGHTINGS["side"], renderer=renderer, seed=9)
    start = ViewParams(perturbed(truth, 9, degrees=4.0, shift=0.02, focal=0.0), sedan.mesh.sphere[0]).dolly_zoom(1.8)
    assert projection_error(sedan, start, truth) > 5.0
    result = register(photo, sedan, init_camera=start, renderer=renderer)
    assert projection_error(sedan, result.camera, truth) < 1.0
    assert result.camera.focal == pytest.approx(truth.focal, rel=0.05)


def test_a_focal_length_outside_the_usual_range_adds_a_probe_to_its_middle(sedan):
    options = RegistrationOptions()
    usual = view(sedan, 60.0, 10.0, focal=1.5 * 640)
    assert probe_factors(usual, options) == list(options.probes.focal_starts)
    for widths in (10.0, 0.4):
        cam = view(sedan, 60.0, 10.0, focal=widths * 640)
        *same, extra = probe_factors(cam, options)
        assert same == list(options.probes.focal_starts)
        assert cam.focal * extra == pytest.approx(np.sqrt(0.7 * 4.0) * 640)


def test_the_papers_nearly_orthographic_start_is_registered(sedan, renderer):
    """The paper's start has f = 10 W; the photo was taken at 1 W."""
    truth = view(sedan, 60.0, 10.0, distance=6.0, focal=640.0)
    photo, _ = synthesize(sedan.mesh, truth, lighting=LIGHTINGS["top"], renderer=renderer, seed=4)
    start = ViewParams(perturbed(truth, 4, degrees=4.0, shift=0.02, focal=0.0), sedan.mesh.sphere[0]).dolly_zoom(10.0)
    assert start.focal == pytest.approx(10 * truth.width)
    result = register(photo, sedan, init_camera=start, renderer=renderer)
    assert projection_error(sedan, result.camera, truth) < 1.0
    assert result.camera.focal == pytest.approx(truth.focal, rel=0.05)
