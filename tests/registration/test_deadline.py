"""The registration's deadline: checked between evaluations, it stops the search at once and
hands over the best pose the finished stages found; synthetic photos."""

from __future__ import annotations

import time

import pytest

from vehicle_pose import register
from vehicle_pose.errors import OutOfTime
from vehicle_pose.registration import deadline as deadline_module
from vehicle_pose.render.synth import LIGHTINGS, synthesize

from helpers import perturbed, projection_error, view


@pytest.fixture(scope="module")
def scene(sedan, renderer):
    """640x480: the shading fit runs three levels (160, 320 and 640 pixels)."""
    truth = view(sedan, 130.0, 12.0, focal=900.0)
    photo, _ = synthesize(sedan.mesh, truth, lighting=LIGHTINGS["side"], renderer=renderer, seed=5)
    return photo, truth


@pytest.mark.parametrize("after", [0.3, 2.0])
def test_a_passed_deadline_stops_the_search_within_a_second(sedan, renderer, scene, after):
    """No hint (the view-sphere search, then the shading polish): stopped while placing,
    ranking or refining. The template match hears the deadline after each share of its
    templates; the longest stretch without a check is now a shading level's start (0.7 s on two
    idle cores). The model's templates are prepared as a worker prepares them."""
    photo, truth = scene
    sedan.templates(renderer)
    t = time.monotonic()
    with pytest.raises(OutOfTime) as caught:
        register(photo, sedan, renderer=renderer, deadline=t + after)
    assert time.monotonic() - (t + after) < 2.0  # 1 s and the test machine's load
    assert caught.value.code == "timeout"


def test_the_deadline_hands_over_the_best_pose_the_finished_stages_found(sedan, renderer, scene, monkeypatch):
    """A start camera: the shading fit's levels are offered as they end; the clock jumps past the
    deadline as the third level starts, and the second level's pose comes back, at the photo's
    size and near the truth."""
    photo, truth = scene
    jumped = [0.0]
    real = deadline_module._clock
    monkeypatch.setattr(deadline_module, "_clock", lambda: real() + jumped[0])

    def progress(stage: str, evaluations: int, loss: float) -> None:
        if stage.startswith("level 3/"):
            jumped[0] = 1e6

    start = perturbed(truth, 2)
    with pytest.raises(OutOfTime) as caught:
        register(photo, sedan, init_camera=start, renderer=renderer, progress=progress,
                 deadline=time.monotonic() + 600.0)
    best = caught.value.camera
    assert best is not None and caught.value.stage == "shading" and "shading" in str(caught.value)
    assert (best.width, best.height) == (640, 480)
    assert projection_error(sedan, best, truth) < 0.5 * projection_error(sedan, start, truth)

