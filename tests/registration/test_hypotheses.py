"""The photo search: hypotheses on the parts' colours, refined on the edges, verified."""

from __future__ import annotations

import numpy as np
import pytest

from vehicle_pose import RegistrationOptions, register
from vehicle_pose.metrics import rotation_error
from vehicle_pose.registration.credibility import confidence
from vehicle_pose.registration.hypotheses import photo_search
from vehicle_pose.render.synth import synthesize_hazard
from vehicle_pose.search.optimize import make_optimizer
from vehicle_pose.search.views import view_camera


def _filling(sedan, azimuth: float):
    """A camera whose view of the sedan fills most of a 320 x 240 frame, as a claims photo does."""
    W, H = 320, 240
    return view_camera(sedan, azimuth, 10.0, 0.0, (12.0, 20.0, W - 12.0, H - 20.0), W, H, 3.0 * W)

# Short searches: the synthetic photos' edges are exact.
_FAST = {"anchor_evaluations": 301, "structure_evaluations": 150, "photo_hypotheses": 3}


@pytest.mark.slow
def test_the_true_view_wins_over_its_twin_on_mirroring_paint(sedan, renderer):
    """Paint that mirrors its surroundings, the vehicle's box known: the hypotheses include the
    true view and views far from it; the refined true view has the lowest structure objective,
    by a margin."""
    photo, mask, truth = synthesize_hazard(sedan.mesh, _filling(sedan, 150.0), "mirror-paint",
                                           renderer=renderer, seed=6)
    ys, xs = np.nonzero(mask)
    box = (float(xs.min()), float(ys.min()), float(xs.max() + 1), float(ys.max() + 1))
    options = RegistrationOptions.from_flat(**_FAST)
    found = photo_search(photo, sedan, [box], options, renderer, make_optimizer(options.optimizer))
    assert len(found.hypotheses) == 3
    objectives = [h.objective for h in found.hypotheses]
    assert objectives == sorted(objectives)
    assert rotation_error(found.best.camera.R, truth.R) < 5.0
    assert any(rotation_error(h.camera.R, truth.R) > 30.0 for h in found.hypotheses)
    checks = found.checks
    assert checks["margin"] > 0.05 and checks["cues_agree"] in (0.0, 1.0) and checks["photo_search"] == 1.0


@pytest.mark.slow
def test_a_photo_the_shading_cannot_explain_is_searched_on_colours_and_edges(sedan, renderer):
    """No hint, paint that mirrors its surroundings, the car filling the frame: the shading
    search's pose is not credible and (with the gate lowered to any loss) not explained by the
    shading, so the photo search runs and its pose, hypotheses, checks and time are reported;
    its confidence follows its two cues.
    (On this synthetic photo the photo search does not find the pose: the mirrored glass has no
    colour of its own; ``docs/decisions/0014-photo-search.md``.)"""
    photo, _, _ = synthesize_hazard(sedan.mesh, _filling(sedan, 120.0), "mirror-paint", renderer=renderer, seed=7)
    result = register(photo, sedan, renderer=renderer,
                      options=RegistrationOptions.from_flat(photo_loss=0.0, **_FAST))
    assert result.start_method == "photo-search" and result.pose_stage == "structure"
    assert "photo_search" in result.timings and result.checks["photo_search"] == 1.0
    assert 0.0 < result.checks["shading_loss"] <= 0.4
    assert result.confidence == pytest.approx(confidence(result.checks))
    assert result.failed == (result.confidence < 0.5) and (result.checks["cues_agree"] == 1.0 or result.failed)
    data = result.to_dict()
    hypotheses = [c for c in data["start"]["candidates"] if c["source"] == "photo-search"]
    assert len(hypotheses) == 3 and all("structure_objective" in c for c in hypotheses)
    without = register(photo, sedan, renderer=renderer,
                       options=RegistrationOptions.from_flat(photo_loss=0.0, photo_search=False, **_FAST))
    assert without.start_method != "photo-search" and "photo_search" not in without.timings
