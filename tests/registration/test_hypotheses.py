"""The photo search: hypotheses on the parts' colours, refined on the edges, verified."""

from __future__ import annotations

import numpy as np
import pytest

from vehicle_pose import RegistrationOptions, register
from vehicle_pose.metrics import rotation_error
from vehicle_pose.registration.credibility import confidence
from vehicle_pose.registration.fit import Fit
from vehicle_pose.registration.hypotheses import photo_pose, photo_search
from vehicle_pose.registration.result import LevelReport
from vehicle_pose.registration.structure import EdgeFit
from vehicle_pose.render.synth import synthesize, synthesize_hazard
from vehicle_pose.search.optimize import make_optimizer
from vehicle_pose.search.views import fit_to_box, view_camera
from vehicle_pose.segment.region import VehicleRegion


def _filling(sedan, azimuth: float):
    """A camera whose view of the sedan fills most of a 320 x 240 frame, as a claims photo does."""
    W, H = 320, 240
    return view_camera(sedan, azimuth, 10.0, 0.0, (12.0, 20.0, W - 12.0, H - 20.0), W, H, 3.0 * W)

# Short searches: the synthetic photos' edges are exact. The photo search spends the two
# anchored searches' budget on one (2 x 150 + 1 = 301 evaluations, 3 generations).
# The photo search is a step of the classic chain (``pose_search="classic"``).
_FAST = {"anchor_evaluations": 151, "structure_runs": 2, "structure_evaluations": 150, "photo_hypotheses": 3,
         "pose_search": "classic"}


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
    assert len(found.hypotheses) == 3 + 1  # 3 distinct views and the best set aside next to the first
    # One anchored search per hypothesis: two from a far start could end in different basins.
    assert [h.structure.levels[0].evaluations for h in found.hypotheses] == [301] * (3 + 1)
    objectives = [h.objective for h in found.hypotheses]
    assert objectives == sorted(objectives)
    assert rotation_error(found.best.camera.R, truth.R) < 5.0
    assert any(rotation_error(h.camera.R, truth.R) > 30.0 for h in found.hypotheses)
    checks = found.checks
    # The edges find the true view; the colours' best hypothesis is another (the mirrored paint
    # and glass have no colour of their own), so the two cues do not agree.
    assert checks["margin"] > 0.05 and checks["cues_agree"] == 0.0 and checks["photo_search"] == 1.0


@pytest.mark.slow
def test_a_photo_the_shading_cannot_explain_is_searched_on_colours_and_edges(sedan, renderer):
    """No hint, paint that mirrors its surroundings, the car filling the frame: the shading
    search's pose is not credible and (with the gate lowered to any loss) not explained by the
    shading, so the photo search runs; its hypotheses, both edge costs and its time are
    reported. Its pose fits the edges better than the shading's, so it is the result; its two
    cues disagree (the mirrored glass has no colour of its own), so it is flagged
    (``docs/decisions/0014-photo-search.md``)."""
    photo, _, _ = synthesize_hazard(sedan.mesh, _filling(sedan, 120.0), "mirror-paint", renderer=renderer, seed=7)
    result = register(photo, sedan, renderer=renderer,
                      options=RegistrationOptions.from_flat(photo_loss=0.0, **_FAST))
    assert "photo_search" in result.timings
    assert result.checks["photo_edges"] < result.checks["shading_edges"]
    assert result.start_method == "photo-search" and result.pose_stage == "structure"
    assert result.confidence == pytest.approx(confidence(result.checks))
    assert result.checks["photo_search"] == 1.0 and 0.0 < result.checks["shading_loss"]
    assert result.checks["cues_agree"] == 0.0 and result.failed
    data = result.to_dict()
    hypotheses = [c for c in data["start"]["candidates"] if c["source"] == "photo-search"]
    assert len(hypotheses) == 3 + 1 and all("structure_objective" in c for c in hypotheses)
    without = register(photo, sedan, renderer=renderer,
                       options=RegistrationOptions.from_flat(photo_loss=0.0, photo_search=False, **_FAST))
    assert without.start_method != "photo-search" and "photo_search" not in without.timings


def _shrunk(sedan, camera):
    """``camera`` with the model moved and scaled into the middle third of the frame: the pose a
    shading search shrinks onto a panel of a real photo."""
    W, H = camera.width, camera.height
    points, centre = sedan.mesh.sample_points(600), sedan.mesh.sphere[0]
    return fit_to_box(camera, points, centre, (W / 3, H / 3, 2 * W / 3, 2 * H / 3), rounds=4, clip=True)


def _shaded(camera, shape):
    """A shading fit that ended at ``camera`` (its loss, as far as the photo pose reads it, 0.5)."""
    level = LevelReport(camera.width, camera.height, 8192, 0, 0, 0.5, 0.0, 0.5)
    return Fit(camera, [level], np.ones(shape, bool), 0.0)


def test_the_edges_score_the_true_pose_below_a_shrunk_one_and_its_twin(sedan, renderer):
    """The one footing on which a photo pose and a shading pose are compared: the chamfer alone,
    with no box, is lowest at the true pose."""
    truth = _filling(sedan, 150.0)
    photo, _ = synthesize(sedan.mesh, truth, renderer=renderer, seed=3)
    twin = view_camera(sedan, 330.0, 10.0, 0.0, (12.0, 20.0, 308.0, 220.0), 320, 240, 3.0 * 320)
    at_truth, shrunk, turned = EdgeFit(photo, sedan, RegistrationOptions(), renderer)(
        [truth, _shrunk(sedan, truth), twin])
    assert at_truth < 0.5 * shrunk and at_truth < 0.5 * turned


@pytest.mark.slow
def test_the_photo_pose_replaces_a_shrunk_shading_pose_and_not_a_right_one(sedan, renderer):
    """A plain photo of a car filling the frame: the photo search finds its view. It replaces a
    shading pose shrunk inside the car (within 5 degrees of the truth, both edge costs
    reported), and leaves the true pose where it is."""
    truth = _filling(sedan, 150.0)
    photo, mask = synthesize(sedan.mesh, truth, renderer=renderer, seed=3)
    options = RegistrationOptions.from_flat(**_FAST)
    optimizer = make_optimizer(options.optimizer)
    region = VehicleRegion.from_mask(mask)
    checks = {"loss": 0.5, "margin": 0.0}
    replaced = photo_pose(photo, sedan, None, region, _shaded(_shrunk(sedan, truth), mask.shape), checks, options,
                          renderer, optimizer)
    assert replaced.fit is not None and rotation_error(replaced.fit.camera.R, truth.R) < 5.0
    assert replaced.checks["photo_edges"] < replaced.checks["shading_edges"]
    assert replaced.checks["shading_loss"] == 0.5 and replaced.checks["photo_search"] == 1.0
    assert replaced.checks["edge_lead"] > 0.35  # a vehicle: far closer than the grid's median view
    assert len(replaced.listed) == 3 + 1 and replaced.seconds > 0.0
    kept = photo_pose(photo, sedan, None, region, _shaded(truth, mask.shape), checks, options, renderer, optimizer)
    assert kept.fit is None and kept.checks["photo_edges"] >= kept.checks["shading_edges"]
    assert kept.checks["shading_information"] >= kept.checks["grid_information"]
    assert kept.checks["loss"] == 0.5 and "photo_search" not in kept.checks and len(kept.listed) == 3 + 1


@pytest.mark.slow
def test_a_shading_pose_the_colours_find_no_vehicle_in_is_replaced_whatever_its_chamfer(sedan, renderer,
                                                                                      monkeypatch):
    """A pose shrunk onto a panel can have the lower chamfer (on a small real photo, its few
    edges on a number plate's). Here the edges are made to prefer the shading pose: the pose
    is still replaced where its parts split off next to nothing of the photo's colours (its
    information below the median view of the grid's), and kept where it is the truth."""

    class ShadingFirst:  # every chamfer 1 but the first camera's (the shading pose's), 0
        def __init__(self, *args, **kwargs):
            pass

        def __call__(self, cameras):
            return [0.0] + [1.0] * (len(cameras) - 1)

    monkeypatch.setattr("vehicle_pose.registration.hypotheses.EdgeFit", ShadingFirst)
    truth = _filling(sedan, 150.0)
    photo, mask = synthesize(sedan.mesh, truth, renderer=renderer, seed=3)
    options = RegistrationOptions.from_flat(**_FAST)
    optimizer = make_optimizer(options.optimizer)
    region = VehicleRegion.from_mask(mask)
    W, H = truth.width, truth.height
    points, centre = sedan.mesh.sample_points(600), sedan.mesh.sphere[0]
    plate = fit_to_box(truth, points, centre, (0.45 * W, 0.6 * H, 0.55 * W, 0.66 * H), rounds=4, clip=True)
    checks = {"loss": 0.5, "margin": 0.0}
    replaced = photo_pose(photo, sedan, None, region, _shaded(plate, mask.shape), checks, options, renderer,
                          optimizer)
    assert replaced.checks["shading_edges"] < replaced.checks["photo_edges"]
    assert replaced.checks["shading_information"] < replaced.checks["grid_information"]
    assert replaced.fit is not None and rotation_error(replaced.fit.camera.R, truth.R) < 5.0
    kept = photo_pose(photo, sedan, None, region, _shaded(truth, mask.shape), checks, options, renderer, optimizer)
    assert kept.checks["shading_information"] >= kept.checks["grid_information"] and kept.fit is None


@pytest.mark.slow
def test_a_photo_of_noise_is_not_a_vehicle_however_the_photo_search_fits_it(sedan, renderer):
    """Coloured noise has edges everywhere: every outline fits them alike, and the photo search's
    pose may still beat the shading pose's chamfer and have its two cues agree by chance. Its
    lead over the grid's median view is small, so the pose is flagged."""
    rng = np.random.default_rng(4)
    photo = (rng.random((60, 80, 3)) * 255).astype(np.uint8).repeat(4, 0).repeat(4, 1)
    result = register(photo, sedan, renderer=renderer,
                      options=RegistrationOptions.from_flat(starts=2, refine=1, max_evaluations=100))
    assert result.failed and result.confidence < 0.5
    if result.start_method == "photo-search":
        assert result.checks["edge_lead"] < 0.2


def test_the_best_view_set_aside_next_to_the_first_hypothesis_is_refined_too(sedan):
    """with_neighbours adds, for each of the first hypotheses, the best-scored view of its box that
    the distinct choice set aside within 25 degrees of it: never a view already chosen, never a
    view of another box, none for the hypotheses after the first ``count``."""
    from vehicle_pose.registration.hypotheses import with_neighbours
    from vehicle_pose.search.views import Candidate, distinct

    boxes = [(100.0, 80.0, 540.0, 400.0), (0.0, 0.0, 639.0, 479.0)]
    rng = np.random.default_rng(1)
    views = [Candidate(view_camera(sedan, az, el, 0.0, boxes[b], 640, 480, 5 * 640.0), "photo-search",
                       score=float(rng.uniform(-1, 0)),
                       detail={"azimuth": az, "elevation": el, "box_index": float(b)})
             for b in (0, 1) for az in range(0, 360, 15) for el in (4.0, 16.0)]
    chosen = distinct(views, 3)

    def ids(cands):
        return [id(c) for c in cands]

    assert ids(with_neighbours(chosen, views, 0)) == ids(chosen)
    out = with_neighbours(chosen, views, 1)
    assert ids(out[:3]) == ids(chosen) and len(out) == 4
    first, added = chosen[0], out[3]
    near = [v for v in views if id(v) not in ids(chosen) and v.detail["box_index"] == first.detail["box_index"]
            and rotation_error(v.camera.R, first.camera.R) < 25.0]
    assert added is min(near, key=lambda v: v.score)
    assert rotation_error(added.camera.R, first.camera.R) < 25.0
    both = with_neighbours(chosen, views, 2)
    assert ids(both[:4]) == ids(out) and len(both) == 5 and len(set(ids(both))) == 5
    assert both[4].detail["box_index"] == chosen[1].detail["box_index"]
