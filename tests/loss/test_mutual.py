"""Material-colour mutual information: the score's algebra and what it tells apart."""

from __future__ import annotations

import numpy as np
import pytest

from vehicle_pose.loss.mutual import MaterialInformation, colour_classes, material_codes, mutual_information
from vehicle_pose.render.synth import synthesize_hazard
from vehicle_pose.search.views import fit_to_box, view_camera

from helpers import view


def test_a_labelling_shares_its_whole_entropy_with_itself_and_none_with_an_independent_one():
    rng = np.random.default_rng(0)
    a = rng.integers(0, 4, size=(64, 64)).astype(np.int32)
    p = np.bincount(a.ravel()) / a.size
    assert mutual_information(a, a, 4) == pytest.approx(-(p * np.log(p)).sum())
    # Every pair of (row band, column band) labels occurs equally often: independent.
    rows = np.repeat(np.arange(4), 16)[:, None] * np.ones((1, 64), int)
    cols = np.ones((64, 1), int) * np.repeat(np.arange(8), 8)[None]
    assert mutual_information(rows.astype(np.int32), cols.astype(np.int32), 8) == pytest.approx(0.0, abs=1e-12)


def test_colour_classes_are_the_same_on_every_call():
    rng = np.random.default_rng(1)
    photo = (rng.random((60, 80, 3)) * 255).astype(np.uint8)
    first = colour_classes(photo, 8)
    assert first.shape == (60, 80) and first.max() == 7
    np.testing.assert_array_equal(first, colour_classes(photo.copy(), 8))
    assert not colour_classes(np.full((10, 10, 3), 90, np.uint8), 8).any()


def test_the_codes_mark_the_parts_and_leave_the_background_zero(sedan, renderer):
    truth = view(sedan, 40.0, 12.0, width=160, height=120, focal=225.0)
    frame = renderer.render(sedan.mesh, truth)
    codes = material_codes(frame)
    assert codes.shape == (120, 160)
    assert np.array_equal(codes > 0, frame.full(frame.labels > 0))
    assert len(np.unique(codes[codes > 0])) >= 3  # body, glass, tyres at least
    shaded = material_codes(frame, shades=16)
    assert len(np.unique(shaded)) >= len(np.unique(codes))


@pytest.mark.parametrize("azimuth", [40.0, 200.0])
def test_the_true_view_scores_above_its_twin_and_a_view_that_fills_the_frame(sedan, renderer, azimuth):
    """On paint that mirrors its surroundings (no lighting explains it) the parts still split
    the photo's colours: the true view scores above the view half a turn away fitted to the
    same box, and above a view so close that the model covers the whole frame."""
    W, H = 320, 240
    truth = view(sedan, azimuth, 12.0, width=W, height=H, focal=450.0)
    photo, mask, truth = synthesize_hazard(sedan.mesh, truth, "mirror-paint", renderer=renderer, seed=2)
    ys, xs = np.nonzero(mask)
    box = (float(xs.min()), float(ys.min()), float(xs.max() + 1), float(ys.max() + 1))
    score = MaterialInformation(photo, sedan.mesh, renderer)
    twin = view_camera(sedan, (azimuth + 180.0) % 360.0, 12.0, 0.0, box, W, H, 450.0)
    filling = fit_to_box(truth, sedan.mesh.sample_points(600), sedan.mesh.sphere[0], (-W, -H, 2.0 * W, 2.0 * H))
    at_truth = score(truth)
    assert at_truth > 0.2
    assert at_truth > 1.1 * score(twin)
    assert score(filling) < 0.1 * at_truth
    assert at_truth <= score.entropy
