"""The confidence of a pose: its fit, its uniqueness, the evidence of a vehicle, its agreement with a box."""

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
    "agree,shading,expected",
    [(1.0, False, 1.0), (2 / 3, False, 1 / 3), (1 / 3, False, 1 / 6), (2 / 3, True, 1.0)],
)
def test_a_pose_the_search_sizes_disagree_on_fails_unless_the_shading_chose_it(agree, shading, expected):
    # A clear lead and margin: only the sizes' vote limits the confidence, and only where the
    # edges chose the pose.
    checks = {"two_way": 0.4, "edge_lead": 0.5, "margin": 0.5, "loss": 0.6, "sizes_agree": agree}
    if shading:
        checks |= {"loss": 0.05, "shading_margin": 0.5}
    assert confidence(checks) == pytest.approx(expected)


@pytest.mark.parametrize("agreement,expected", [(None, 1.0), (0.9, 1.0), (0.7, 1.0), (0.6, 0.75), (0.5, 0.5),
                                                (0.45, 0.375), (0.18, 0.0)])
def test_a_pose_that_does_not_match_the_clients_box_is_not_credible(agreement, expected):
    # A start camera's pose with clear edge evidence: only its agreement with the client's box
    # (the IoU of the projection's box with it) limits the confidence, 0.5 at IoU 0.5.
    checks = {"two_way": 0.4, "edge_lead": 0.5, "loss": 0.6, "hinted": 1.0}
    if agreement is not None:
        checks["box_agreement"] = agreement
    assert confidence(checks) == pytest.approx(expected)
    assert (confidence(checks) >= 0.5) == (agreement is None or agreement >= 0.5)


@pytest.mark.parametrize("two_way,lead,credible", [(0.4, 0.0, True), (0.4, 0.5, True), (2.0, 0.0, False),
                                                   (0.9, 0.5, False)])
def test_the_shading_stands_in_for_the_edges_lead_not_for_the_edges(two_way, lead, credible):
    # A start camera's pose whose shading explains the photo (loss 0.05 of its maximum): a matte
    # car whose outline leads no other view is credible, a pose that explains none of the edges
    # in its box (a smooth background's shading) is not.
    checks = {"two_way": two_way, "edge_lead": lead, "loss": 0.05, "hinted": 1.0}
    assert (confidence(checks) >= 0.5) == credible
