"""The edge alignment term: a directional chamfer of the model's edges against the photo's."""

from __future__ import annotations

import numpy as np
import pytest

from vehicle_pose.loss.edges import ORIENTATIONS, EdgeLoss, TwoWayChamfer, photo_edges
from vehicle_pose.render.renderer import Frame
from vehicle_pose.render.synth import LIGHTINGS, synthesize

from helpers import view

H, W = 120, 160


def _square_photo(x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
    img = np.full((H, W, 3), 40, np.uint8)
    img[y0:y1, x0:x1] = 200
    return img


def _square_frame(x0: int, y0: int, x1: int, y1: int) -> Frame:
    """A flat square of one material facing the camera, as the renderer returns it (window cut
    to the photo)."""
    cx0, cy0, cx1, cy1 = max(x0, 0), max(y0, 0), min(x1, W), min(y1, H)
    h, w = cy1 - cy0, cx1 - cx0
    attrs = np.zeros((h, w, 4), np.float32)
    attrs[..., 0] = 1.0
    attrs[..., 3] = -1.0
    return Frame(attrs, np.ones((h, w), np.uint8), cx0, cy0, W, H)


def test_aligned_outline_costs_almost_nothing_and_a_shift_costs_more():
    loss = EdgeLoss(_square_photo(40, 30, 110, 90))
    aligned = loss(_square_frame(40, 30, 110, 90))
    shifted = loss(_square_frame(46, 30, 116, 90))
    far = loss(_square_frame(0, 0, 30, 25))
    assert aligned * loss.tau < 1.0  # under a pixel from the photo's edges on average
    assert aligned < shifted < far
    assert far > 0.9


def test_an_edge_of_another_orientation_does_not_count():
    photo = np.full((H, W, 3), 40, np.uint8)
    for x in range(20, W, 12):
        photo[:, x:x + 6] = 200  # vertical stripes: edges with horizontal gradients only
    dist = photo_edges(photo).distance
    assert dist.shape == (ORIENTATIONS, H, W)
    assert dist[0, H // 2, 20] < 1.5  # same orientation: on the edge
    assert dist[ORIENTATIONS // 2, H // 2, 20] > 50  # perpendicular: no edge anywhere
    # The square's left and right sides lie on stripe edges, its top and bottom cross them:
    # half its outline finds nothing of its orientation.
    cost = EdgeLoss(photo)(_square_frame(20, 30, 62, 90))
    assert 0.3 < cost < 0.7


def test_the_photo_border_is_not_an_edge_of_the_model():
    photo = _square_photo(60, 30, W, 90)  # the square runs off the right border
    loss = EdgeLoss(photo)
    assert loss(_square_frame(60, 30, W + 40, 90)) * loss.tau < 1.0


def test_edges_beyond_the_foreground_do_not_hold_the_model():
    photo = _square_photo(20, 30, 70, 90)
    photo[30:90, 100:150] = 200  # a second object, beyond the foreground
    fg = np.zeros((H, W), bool)
    fg[30:90, 20:70] = True
    masked, unmasked = EdgeLoss(photo, foreground=fg), EdgeLoss(photo)
    other = _square_frame(100, 30, 150, 90)
    assert unmasked(other) * unmasked.tau < 1.0
    assert masked(other) > 0.5
    assert masked(_square_frame(20, 30, 70, 90)) * masked.tau < 1.0


def test_a_frame_without_edges_costs_one():
    loss = EdgeLoss(_square_photo(40, 30, 110, 90))
    assert loss(Frame.empty(W, H)) == 1.0
    assert loss(_square_frame(0, 0, 2, 2)) == 1.0


def test_rendered_model_is_lowest_at_its_true_pose(sedan, renderer):
    truth = view(sedan, 60.0, 15.0, width=320, height=240, focal=450.0)
    photo, _ = synthesize(sedan.mesh, truth, lighting=LIGHTINGS["side"], renderer=renderer, seed=4)
    loss = EdgeLoss(photo)
    at_truth = loss(renderer.render(sedan.mesh, truth))
    for azimuth in (52.0, 68.0):
        assert loss(renderer.render(sedan.mesh, view(sedan, azimuth, 15.0, width=320, height=240, focal=450.0))) \
            > at_truth + 0.05
    assert at_truth < 0.25


@pytest.mark.parametrize("bad", [np.zeros((0, 0, 3), np.uint8), np.zeros((H, W), np.uint8), np.zeros((H, W, 3))])
def test_a_photo_that_is_not_rgb_bytes_is_refused(bad):
    with pytest.raises(ValueError, match="photo"):
        EdgeLoss(bad)


def test_a_crease_is_an_edge_only_when_sharper_than_the_threshold():
    # Two flat halves of one material meeting at a 60-degree crease down the middle, over a
    # photo whose only edges are the outline: the crease costs where it counts as an edge.
    attrs = np.zeros((60, 80, 4), np.float32)
    attrs[..., 0] = 1.0
    turn = np.radians(30.0)
    attrs[:, :40, 1:] = (-np.sin(turn), 0.0, -np.cos(turn))
    attrs[:, 40:, 1:] = (np.sin(turn), 0.0, -np.cos(turn))
    frame = Frame(attrs, np.ones((60, 80), np.uint8), 40, 30, W, H)
    photo = _square_photo(40, 30, 120, 90)
    sharp, blunt = EdgeLoss(photo, crease=0.6)(frame), EdgeLoss(photo, crease=2.0)(frame)
    assert blunt * EdgeLoss(photo).tau < 1.0
    assert sharp > blunt + 0.05


def _windowed_frame(x0: int, y0: int, x1: int, y1: int, window: tuple[int, int, int, int]) -> Frame:
    """:func:`_square_frame` with a darker material inside ``window`` (a material edge)."""
    frame = _square_frame(x0, y0, x1, y1)
    wx0, wy0, wx1, wy1 = window
    frame.attrs[wy0 - y0:wy1 - y0, wx0 - x0:wx1 - x0, 0] = 0.3
    frame.attrs[wy0 - y0:wy1 - y0, wx0 - x0:wx1 - x0, 3] = -0.3
    return frame


def test_the_converse_charges_the_photos_edges_that_the_model_leaves_unexplained():
    photo = _square_photo(40, 30, 110, 90)
    photo[45:75, 55:95] = 90  # a dark window inside the body
    chamfer = TwoWayChamfer(photo)
    plain_forward, plain_reverse = chamfer.parts(_square_frame(40, 30, 110, 90))
    forward, reverse = chamfer.parts(_windowed_frame(40, 30, 110, 90, (55, 45, 95, 75)))
    # Both outlines lie on the photo's edges; only the model with the window explains them all.
    assert plain_forward * chamfer.tau < 1.0 and forward * chamfer.tau < 1.0
    assert reverse * chamfer.tau < 1.0 < plain_reverse * chamfer.tau
    assert chamfer(_windowed_frame(40, 30, 110, 90, (55, 45, 95, 75))) < chamfer(_square_frame(40, 30, 110, 90))
    # A model half a square off explains neither way.
    assert min(chamfer.parts(_square_frame(75, 30, 145, 90))) > 0.1


def test_the_converse_counts_the_region_and_charges_the_rest_as_clutter():
    photo = _square_photo(20, 30, 70, 90)
    photo[40:80, 110:150] = 220  # a second bright square, away from the model
    frame = _square_frame(20, 30, 70, 90)
    whole = TwoWayChamfer(photo)
    everywhere = whole.parts(frame)[1]
    region = (10.0, 20.0, 80.0, 100.0)
    inside = TwoWayChamfer(photo, region=region).parts(frame)[1]
    assert inside * whole.tau < 1.0 < everywhere * whole.tau  # the other square's edges are unexplained
    cluttered = TwoWayChamfer(photo, region=region, among=(0.0, 0.0, W - 1.0, H - 1.0), clutter=0.5)
    n_in, n_out = cluttered.rows.size, cluttered.outside
    assert n_out > 0 and abs(cluttered.parts(frame)[1] - (inside * n_in + 0.5 * n_out) / (n_in + n_out)) < 1e-9
    assert TwoWayChamfer(photo).parts(Frame.empty(W, H)) == (1.0, 1.0)


def test_colour_edges_find_an_outline_of_equal_luminance():
    photo = np.full((H, W, 3), 0, np.uint8)
    photo[..., 1] = 100
    photo[30:90, 40:110] = (200, 0, 0)  # red on green, about the same luminance
    assert abs(float(photo[60, 60] @ [0.299, 0.587, 0.114]) - float(photo[5, 5] @ [0.299, 0.587, 0.114])) < 2
    assert not photo_edges(photo).edges.any()
    colour = photo_edges(photo, colour=True)
    assert colour.edges[28:32, 60:90].any(axis=0).all() and colour.edges[60, 38:42].any()
    assert colour.bins[colour.edges].min() >= 0 and (colour.bins[~colour.edges] == -1).all()
