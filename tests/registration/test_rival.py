"""Without a hint, where the shading fit confirms a pose, the shading also judges its rival
(docs/decisions/0033-the-shading-judges-its-rival.md): which of the two wins, and the margin
that stands for the pose's uniqueness."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vehicle_pose import Camera, RegistrationOptions
from vehicle_pose.errors import PoseError
from vehicle_pose.registration.credibility import confidence
from vehicle_pose.registration.fit import Fit
from vehicle_pose.registration.result import LevelReport
from vehicle_pose.registration.sphere import Pose, _against_rival

W, H = 320, 240
WORK = np.zeros((H, W, 3), np.uint8)
OPTIONS = RegistrationOptions()


def _camera(azimuth: float) -> Camera:
    K = np.array([[400.0, 0.0, W / 2], [0.0, 400.0, H / 2], [0.0, 0.0, 1.0]])
    R = Rotation.from_euler("y", azimuth, degrees=True).as_matrix()
    return Camera(K, R, np.array([0.0, 0.0, 10.0]), W, H)


def _fit(azimuth: float, loss: float) -> Fit:
    return Fit(_camera(azimuth), [LevelReport(W, H, 100, 10, 0, loss, 0.1, loss)], np.ones((H, W), bool), 0.0)


def _poses(*azimuths: float) -> list[Pose]:
    return [Pose(_camera(a), 0, 0, 0.5) for a in azimuths]


class _Polish:
    """A stand-in for the shading fit: each start's polished pose, and which starts it ran from."""

    def __init__(self, ends: dict[float, tuple[float, float]]) -> None:
        self.ends, self.ran = ends, []

    def __call__(self, pose: Pose) -> Fit:
        azimuth = round(float(Rotation.from_matrix(pose.camera.R).as_euler("yxz", degrees=True)[0]), 3)
        self.ran.append(azimuth)
        return _fit(*self.ends[azimuth])


def test_a_rival_the_shading_explains_worse_leaves_the_pose_with_their_margin():
    bests, polish = _poses(0.0, 5.0, 180.0), _Polish({180.0: (178.0, 0.08)})
    fitted, k, margin = _against_rival(_fit(1.0, 0.04), 0, bests, [0.2, 0.3, 0.25], polish, WORK, OPTIONS)
    assert polish.ran == [180.0]  # the pose 5 degrees away is the same pose, not a rival
    assert k == 0 and fitted.loss == 0.04 and margin == pytest.approx(0.5)


def test_a_rival_the_shading_explains_better_wins():
    bests, polish = _poses(0.0, 180.0), _Polish({180.0: (179.0, 0.03)})
    fitted, k, margin = _against_rival(_fit(1.0, 0.06), 0, bests, [0.2, 0.25], polish, WORK, OPTIONS)
    assert k == 1 and fitted.loss == 0.03 and margin == pytest.approx(0.5)


def test_a_rival_whose_polish_ends_at_the_pose_is_the_same_pose_found_twice():
    bests, polish = _poses(0.0, 40.0), _Polish({40.0: (2.0, 0.05)})
    fitted, k, margin = _against_rival(_fit(1.0, 0.06), 0, bests, [0.2, 0.25], polish, WORK, OPTIONS)
    assert margin == 1.0 and k == 1 and fitted.loss == 0.05  # the better polish of the one pose stands


@pytest.mark.parametrize("azimuths,shares", [((0.0, 10.0), [0.2, 0.1]), ((0.0, 180.0), [0.2, 0.6])])
def test_no_rival_is_polished_where_none_is_apart_or_the_shading_cannot_explain_it(azimuths, shares):
    polish = _Polish({})
    fitted, k, margin = _against_rival(_fit(1.0, 0.06), 0, _poses(*azimuths), shares, polish, WORK, OPTIONS)
    assert polish.ran == [] and k == 0 and margin == 1.0 and fitted.loss == 0.06


def test_a_rival_no_fit_can_start_from_is_no_rival():
    def polish(pose: Pose) -> Fit:
        raise PoseError("the start pose does not show the left side's wheels")

    fitted, k, margin = _against_rival(_fit(1.0, 0.06), 0, _poses(0.0, 180.0), [0.2, 0.25], polish, WORK, OPTIONS)
    assert k == 0 and margin == 1.0 and fitted.loss == 0.06


@pytest.mark.parametrize("shading_margin,credible", [(0.5, True), (0.2, True), (0.05, False), (-0.1, False)])
def test_where_the_shading_judged_the_rival_its_margin_is_the_uniqueness(shading_margin, credible):
    # The edges' margin is small either way (the shading, not the edges, chose the pose); a
    # good fit and a vehicle along the outline.
    checks = {"two_way": 0.4, "edge_lead": 0.4, "loss": 0.03, "margin": 0.0, "shading_margin": shading_margin}
    assert (confidence(checks) >= 0.5) == credible
    without = {k: v for k, v in checks.items() if k != "shading_margin"}
    assert confidence(without) < 0.5
