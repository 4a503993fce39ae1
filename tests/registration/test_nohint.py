"""Registration without a hint by the classic chain (``pose_search="classic"``: region, wheels and
view grid, multi-start refinement), end to end on synthetic ground truth; the default view-sphere
search is tested in ``test_sphere.py``."""

from __future__ import annotations

import numpy as np
import pytest

from vehicle_pose import RegistrationOptions, register
from vehicle_pose.render.synth import LIGHTINGS, background, synthesize
from vehicle_pose.search.views import (
    view_camera,
)

from helpers import projection_error, view

CLASSIC = RegistrationOptions.from_flat(pose_search="classic")


@pytest.mark.slow
@pytest.mark.parametrize("model_id,azimuth,elevation", [("sedan", 120.0, 15.0), ("van", 320.0, 20.0)])
def test_registers_without_any_hint(library, renderer, model_id, azimuth, elevation):
    model = library.load(model_id)
    truth = view(model, azimuth, elevation, focal=1000.0, distance=11.0)
    photo, _ = synthesize(model.mesh, truth, lighting=LIGHTINGS["top"], renderer=renderer, seed=8)
    result = register(photo, model, renderer=renderer, options=CLASSIC)
    assert projection_error(model, result.camera, truth) < 2.0
    assert result.start_source == "none" and result.start_method in ("view-search", "wheels")
    assert not result.failed and result.confidence is not None and result.confidence >= 0.5
    d = result.to_dict()
    assert d["failed"] is False and d["start"]["candidates"] and d["checks"]["region_iou"] > 0.9
    # The edge term refines a given start only; the no-hint chain runs on the loss alone.
    assert RegistrationOptions().terms.edge_weight > 0 and d["options"]["edge_weight"] == 0.0
    assert all(level["objective"] == level["loss"] for level in d["levels"])


@pytest.mark.slow
def test_a_near_rear_view_with_a_short_lens_is_refined_down_its_valley(library, renderer):
    """Seen from behind through a 0.8-width lens, elevation, height, scale and focal length trade
    against each other along a narrow valley: refined by the simplex the pose stops several
    pixels short of the truth, by CMA-ES (the default) it gets there."""
    hatchback = library.load("hatchback")
    W, H = 320, 240
    bw, bh = 0.48 * W, 0.384 * W
    box = (W / 2 - bw / 2, H / 2 - bh / 2, W / 2 + bw / 2, H / 2 + bh / 2)
    truth = view_camera(hatchback, 179.0, 10.0, 0.0, box, W, H, 0.82 * W)
    photo, _ = synthesize(hatchback.mesh, truth, lighting=LIGHTINGS["side"], renderer=renderer, seed=5)
    cma = register(photo, hatchback, renderer=renderer, options=CLASSIC)
    simplex = register(photo, hatchback, renderer=renderer,
                       options=RegistrationOptions.from_flat(pose_search="classic", refine_optimizer="nelder-mead"))
    assert projection_error(hatchback, cma.camera, truth) < 2.0 and not cma.failed
    assert projection_error(hatchback, simplex.camera, truth) > 4.0
    assert cma.loss < simplex.loss
    with pytest.raises(ValueError, match="unknown refine_optimizer"):
        register(photo, hatchback, renderer=renderer,
                 options=RegistrationOptions.from_flat(pose_search="classic", refine_optimizer="bfgs"))


@pytest.mark.slow
def test_a_second_pass_searches_again_and_keeps_the_lower_loss(library, renderer):
    hatchback = library.load("hatchback")
    truth = view(hatchback, 230.0, 14.0, focal=500.0, distance=11.0, width=320, height=240)
    photo, _ = synthesize(hatchback.mesh, truth, lighting=LIGHTINGS["side"], renderer=renderer, seed=12)
    quick = RegistrationOptions.from_flat(pose_search="classic", starts=3, refine=1, max_size=320, screen_size=160)
    once = register(photo, hatchback, renderer=renderer, options=quick)
    assert "passes" not in once.checks and "second_pass" not in once.timings
    # Every pose is below this confidence, so the second pass always runs.
    twice = register(photo, hatchback, renderer=renderer, options=quick.replace(min_confidence=1.01))
    assert twice.checks["passes"] == 2 and twice.timings["second_pass"] > 0 and twice.failed
    assert twice.loss <= once.loss and twice.evaluations > once.evaluations
    assert projection_error(hatchback, twice.camera, truth) < 2.0


@pytest.mark.slow
def test_a_photo_without_a_vehicle_is_flagged_failed(library, renderer):
    rng = np.random.default_rng(4)
    photo = (np.clip(background(480, 640, rng), 0, 1) * 255).astype(np.uint8)
    result = register(photo, library.load("sedan"), renderer=renderer,
                      options=RegistrationOptions.from_flat(starts=2, refine=1, max_evaluations=150))
    assert result.failed and result.confidence is not None and result.confidence < 0.5
