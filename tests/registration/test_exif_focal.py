"""The phone's focal length: the EXIF focal length holds the search without a start camera, a
start camera's wins, and EXIF that cannot be right is reported and ignored; synthetic photos."""

from __future__ import annotations

import pytest

from vehicle_pose import RegistrationOptions, register
from vehicle_pose.photo import ExifFocal
from vehicle_pose.render.synth import LIGHTINGS, synthesize
from vehicle_pose.search.views import view_camera

from helpers import perturbed, projection_error

W, H = 320, 240


@pytest.fixture(scope="module")
def long_lens(sedan, renderer):
    """A photo of the sedan through a long lens (2.4 image widths, 90 mm equivalent) and its truth."""
    truth = view_camera(sedan, 225.0, 12.0, 0.0, (50.0, 60.0, 270.0, 190.0), W, H, 2.4 * W)
    photo, _ = synthesize(sedan.mesh, truth, lighting=LIGHTINGS["side"], renderer=renderer, seed=11)
    return photo, truth


@pytest.mark.slow
def test_the_exif_focal_length_holds_the_search_without_a_hint(sedan, renderer, long_lens):
    photo, truth = long_lens
    # EXIF 3 % off the truth, as a rounded 35 mm equivalent and its conventions leave it.
    exif = ExifFocal(widths=1.03 * truth.focal / W, form="35mm", equivalent_mm=93.0)
    result = register(photo, sedan, renderer=renderer, exif=exif)
    focal = result.focal
    assert focal["source"] == "exif" and focal["exif"]["pixels"] == pytest.approx(1.03 * truth.focal)
    assert abs(result.camera.focal / truth.focal - 1.0) < 0.03 * RegistrationOptions().search.exif_tolerance + 0.005
    assert projection_error(sedan, result.camera, truth) < 1.5 and not result.failed
    data = result.to_dict()
    assert data["focal"]["source"] == "exif" and data["warnings"] == []


@pytest.mark.slow
def test_the_shading_refines_an_exif_focal_length_a_phone_rounded(sedan, renderer):
    """A matte photo through a phone's main lens (one image width, 35 mm equivalent) whose EXIF
    is 4 % off (the 35 mm conventions of a 4:3 sensor): held at it, the focal length ends 4 %
    off; refined by the shading under the EXIF's prior, within 1.5 %, and the vertices nearer
    the truth. (Through a long lens the shading hardly tells focal lengths 4 % apart: the
    refinement leaves the EXIF's.)"""
    truth = view_camera(sedan, 225.0, 12.0, 0.0, (50.0, 60.0, 270.0, 190.0), W, H, 1.0 * W)
    photo, _ = synthesize(sedan.mesh, truth, lighting=LIGHTINGS["side"], renderer=renderer, seed=11)
    exif = ExifFocal(widths=1.04 * truth.focal / W, form="35mm", equivalent_mm=36.0)
    held = register(photo, sedan, renderer=renderer, exif=exif,
                    options=RegistrationOptions.from_flat(exif_refine=0.0))
    refined = register(photo, sedan, renderer=renderer, exif=exif)
    assert RegistrationOptions().search.exif_refine > 0
    assert held.pose_stage == refined.pose_stage == "shading"
    assert abs(held.camera.focal / truth.focal - 1.04) < 0.002
    assert abs(refined.camera.focal / truth.focal - 1.0) < 0.015
    assert projection_error(sedan, refined.camera, truth) < projection_error(sedan, held.camera, truth)
    assert refined.focal["source"] == "exif" and refined.focal["pixels"] == pytest.approx(refined.camera.focal)
    assert refined.focal["exif"]["pixels"] == pytest.approx(1.04 * truth.focal)


@pytest.mark.slow
def test_a_start_camera_wins_over_the_exif_focal_length(sedan, renderer, long_lens):
    photo, truth = long_lens
    start = perturbed(truth, 4)
    wrong = ExifFocal(widths=0.5 * truth.focal / W, form="35mm", equivalent_mm=45.0)
    result = register(photo, sedan, init_camera=start, renderer=renderer, exif=wrong)
    assert result.focal["source"] == "searched" and result.focal["exif"]["widths"] == pytest.approx(wrong.widths)
    assert abs(result.camera.focal / truth.focal - 1.0) < 0.1
    assert projection_error(sedan, result.camera, truth) < 1.5


def test_exif_that_cannot_be_right_is_a_warning_and_the_focal_length_is_searched(sedan, renderer, long_lens):
    photo, truth = long_lens
    absurd = ExifFocal(form="35mm", equivalent_mm=1000.0, warning="the EXIF focal length (1000 mm) cannot be")
    start = perturbed(truth, 5)
    result = register(photo, sedan, init_camera=start, renderer=renderer, exif=absurd,
                      options=RegistrationOptions.from_flat(max_evaluations=30, fine_evaluations=30))
    assert result.focal["source"] == "searched" and result.warnings == [absurd.warning]
    assert result.to_dict()["warnings"] == [absurd.warning]
    assert result.to_dict()["focal"]["exif"]["equivalent_mm"] == 1000.0


def test_without_exif_the_result_says_the_focal_length_was_searched(sedan, renderer, long_lens):
    photo, truth = long_lens
    result = register(photo, sedan, init_camera=perturbed(truth, 6), renderer=renderer,
                      options=RegistrationOptions.from_flat(max_evaluations=30, fine_evaluations=30))
    assert result.focal["source"] == "searched" and result.focal["exif"] is None and result.warnings == []
    assert result.focal["pixels"] == pytest.approx(result.camera.focal)
