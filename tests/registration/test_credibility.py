"""The confidence of a pose found without a start camera."""

from __future__ import annotations

import pytest

from vehicle_pose.registration.credibility import confidence


@pytest.mark.parametrize(
    "checks,credible",
    [
        ({"loss": 0.05, "margin": 0.5, "agreement": 0.0, "region_iou": 0.95}, True),
        # A distinct pose fits as well: ambiguous however many starts ended at the winner.
        ({"loss": 0.05, "margin": 0.0, "agreement": 0.67, "region_iou": 0.95}, False),
        ({"loss": 0.25, "margin": 0.5, "agreement": 0.0, "region_iou": 0.95}, False),  # poor fit
        ({"loss": 0.05, "margin": 0.05, "agreement": 0.0, "region_iou": 0.95}, False),  # a rival as good
        ({"loss": 0.05, "margin": 0.5, "agreement": 0.0, "region_iou": 0.55}, False),  # not the vehicle
        ({"loss": 0.05, "margin": 0.5}, False),  # no region measured
    ],
)
def test_confidence_needs_fit_uniqueness_and_region(checks, credible):
    value = confidence(checks)
    assert 0.0 <= value <= 1.0 and (value >= 0.5) == credible


@pytest.mark.parametrize(
    "margin,agree,lead,expected",
    [(0.35, 1.0, 0.4, 1.0), (0.15, 1.0, 0.4, 0.75), (-0.05, 1.0, 0.4, 0.5), (0.35, 0.0, 0.4, 0.45),
     (0.15, 0.0, 0.4, 0.225), (0.35, 1.0, 0.2, 0.5), (0.35, 1.0, 0.14, 0.3), (0.35, 1.0, None, 0.0)],
)
def test_a_photo_search_pose_is_credible_when_its_two_cues_agree_on_a_vehicle(margin, agree, lead, expected):
    # The photo search's pose has no credible loss and no usable region: the cues decide, as
    # far as the edges show a vehicle at all (a lead over the grid's median view).
    checks = {"photo_search": 1.0, "margin": margin, "cues_agree": agree, "loss": 0.8, "region_iou": 0.1}
    if lead is not None:
        checks["edge_lead"] = lead
    assert confidence(checks) == pytest.approx(expected)
    assert (confidence(checks) >= 0.5) == (agree == 1.0 and lead is not None and lead >= 0.2)


@pytest.mark.parametrize(
    "seen,expected",
    [(1.0, 1.0), (0.29, 1.0), (0.25, 1.0), (0.15, 0.5), (0.075, 0.125), (0.0, 0.0)],
)
def test_edge_evidence_needs_the_outline_in_view(seen, expected):
    # A model larger than the photo fits inner edges anywhere; its outline, outside the frame
    # all round, shows nothing to verify. A car cut by the frame by a third keeps 0.3-0.7 of it.
    checks = {"two_way": 0.45, "edge_lead": 0.45, "loss": 0.8, "margin": 0.5, "outline_seen": seen}
    assert confidence(checks) == pytest.approx(expected)
    assert confidence({**checks, "hinted": 1.0}) == pytest.approx(expected)
    assert confidence({**checks, "loss": 0.05}) == 1.0  # where the shading explains the photo, it is evidence


def test_the_share_of_the_outline_in_view(sedan, renderer):
    """A whole car in view shows all its outline; cut by the frame, part; a model larger than
    the photo (the camera close, looking at the door), none."""
    from vehicle_pose.geometry.camera import Camera, look_at_camera
    from vehicle_pose.registration.sphere import outline_seen

    centre, radius = sedan.mesh.sphere
    whole = look_at_camera(centre, [1, 0, 0], [0, 0, 1], azimuth_deg=60, elevation_deg=15, distance=4 * radius,
                           focal=400, width=320, height=240)
    K = whole.K.copy()
    K[0, 2] += 110  # the car's centre 110 px right of the middle: its front out of the frame
    cut = Camera(K, whole.R, whole.t, 320, 240)
    near = look_at_camera(centre, [1, 0, 0], [0, 0, 1], azimuth_deg=90, elevation_deg=5, distance=4 * radius,
                          focal=2400, width=320, height=240)
    assert outline_seen(sedan, whole, renderer) > 0.95
    assert 0.3 < outline_seen(sedan, cut, renderer) < 0.9
    assert outline_seen(sedan, near, renderer) < 0.05
