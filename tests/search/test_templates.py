"""Edge templates over a view sphere: built once, matched with their place and scale, kept."""

from __future__ import annotations

import numpy as np
import pytest

from vehicle_pose.loss.edges import photo_edges
from vehicle_pose.metrics import rotation_error
from vehicle_pose.model.library import model_from_mesh
from vehicle_pose.model.store import ModelStore
from vehicle_pose.render.synth import LIGHTINGS, synthesize
from vehicle_pose.search import templates as templates_module
from vehicle_pose.search.templates import TemplateGrid, ViewTemplates, match, turn_to

GRID = TemplateGrid(azimuth_step=30.0, elevations=(8.0,), distances=(4.0,), points=128)


@pytest.fixture(scope="module")
def templates(sedan, renderer) -> ViewTemplates:
    return ViewTemplates.build(sedan, renderer, GRID)


def _photo(sedan, renderer, index: int, templates: ViewTemplates, focal: float, u: float, v: float,
           size: tuple[int, int] = (320, 240)):
    truth = templates.camera(index, focal, u, v, ((size[0] - 1) / 2, (size[1] - 1) / 2), *size)
    photo, _ = synthesize(sedan.mesh, truth, lighting=LIGHTINGS["side"], renderer=renderer, seed=3)
    return photo, truth


def test_templates_hold_every_view_of_the_grid(templates):
    assert len(templates) == 12
    assert templates.offsets[-1] == len(templates.points) == len(templates.bins)
    counts = np.diff(templates.offsets)
    assert counts.min() > 32 and counts.max() <= GRID.points
    assert np.all(templates.boxes[:, 2] > templates.boxes[:, 0])
    # Each template's camera looks along its axis at the model's centre.
    for R in templates.rotations:
        assert abs(np.linalg.det(R) - 1.0) < 1e-9


def test_turn_to_takes_the_axis_to_the_ray():
    ray = np.array([0.3, -0.2, 1.0])
    assert np.allclose(turn_to(ray) @ [0.0, 0.0, 1.0], ray / np.linalg.norm(ray))
    assert np.allclose(turn_to(np.array([0.0, 0.0, 2.0])), np.eye(3))


def test_a_placed_template_shows_the_model_where_it_was_placed(sedan, templates):
    cam = templates.camera(4, 300.0, 120.0, 140.0, (159.5, 119.5), 320, 240)
    centre = cam.project(templates.centre[None])[0]
    assert np.allclose(centre, [120.0, 140.0], atol=1e-6)
    assert abs(cam.focal - 300.0) < 1e-9


def test_the_true_view_matches_best_at_its_place_and_scale(sedan, renderer, templates):
    photo, truth = _photo(sedan, renderer, 4, templates, 260.0, 170.0, 125.0)
    edges = photo_edges(photo)
    tau = 0.05 * float(np.hypot(320, 240))
    frame = (0.0, 0.0, 319.0, 239.0)
    uv = truth.project(sedan.mesh.sample_points(600))
    box = (float(uv[:, 0].min()), float(uv[:, 1].min()), float(uv[:, 0].max()), float(uv[:, 1].max()))
    placed = match(templates, edges.distance, tau, [box, frame], scales=(0.8, 1.3), min_iou=0.3)
    best = int(np.argmin(placed.cost[:, 0]))
    assert best == 4
    assert abs(placed.focal[best, 0] / 260.0 - 1.0) < 0.1
    assert np.hypot(placed.u[best, 0] - 170.0, placed.v[best, 0] - 125.0) < 8.0
    # The neighbouring views of the grid, 30 degrees off, cost more than the true one.
    assert placed.cost[best, 0] < 0.8 * min(placed.cost[3, 0], placed.cost[5, 0])


def test_targets_placed_a_share_at_a_time_give_the_same_placements(sedan, renderer, templates, monkeypatch):
    """With ``between`` (a deadline's check), each target is placed on its own, a share of the
    templates at a time, ``between`` heard after each share: the same arrays."""
    photo, _ = _photo(sedan, renderer, 4, templates, 260.0, 170.0, 125.0)
    edges = photo_edges(photo)
    targets = [(0.0, 0.0, 319.0, 239.0), (60.0, 50.0, 280.0, 200.0), (100.0, 70.0, 240.0, 180.0)]
    allowed = np.ones(len(templates), bool)
    allowed[1] = False
    together = match(templates, edges.distance, 16.0, targets, allowed=allowed)
    monkeypatch.setattr(templates_module, "_SHARE", 3)
    calls: list[int] = []
    apart = match(templates, edges.distance, 16.0, targets, allowed=allowed, between=lambda: calls.append(1))
    assert len(calls) == len(targets) * -(-(len(templates) - 1) // 3)
    assert np.all(np.isinf(apart.cost[1]))
    for name in ("cost", "focal", "u", "v"):
        np.testing.assert_array_equal(getattr(together, name), getattr(apart, name))


def test_a_car_cut_by_the_frame_is_a_template_cut_by_the_frame(sedan, renderer, templates):
    """About a third of the car is beyond the left border: the template placed there, scored on
    its points inside, still wins, at the car's true scale (not shrunk into the frame)."""
    photo, truth = _photo(sedan, renderer, 3, templates, 300.0, 40.0, 120.0)
    uv = truth.project(sedan.mesh.sample_points(600))
    assert uv[:, 0].min() < -40
    edges = photo_edges(photo)
    tau = 0.05 * float(np.hypot(320, 240))
    visible = (0.0, float(max(0, uv[:, 1].min())), float(uv[:, 0].max()), float(min(239, uv[:, 1].max())))
    placed = match(templates, edges.distance, tau, [visible], scales=(0.8, 2.0))
    best = int(np.argmin(placed.cost[:, 0]))
    assert rotation_error(templates.rotations[best], templates.rotations[3]) < 1.0
    assert abs(placed.focal[best, 0] / 300.0 - 1.0) < 0.12


def test_a_placement_costs_the_mean_truncated_distance_at_its_points_in_view(sedan, renderer, templates):
    """The compiled placement's cost, worked again here: each of the template's points turned
    with the placed camera, projected, rounded to its pixel and read in its orientation's
    distance map, truncated at tau; the mean over those in the frame (part of the car is beyond
    the left border, so some are not)."""
    photo, _ = _photo(sedan, renderer, 3, templates, 300.0, 40.0, 120.0)
    edges = photo_edges(photo)
    tau = 14.0
    placed = match(templates, edges.distance, tau, [(0.0, 30.0, 200.0, 210.0)], scales=(0.8, 2.0))
    costs = np.minimum(edges.distance, np.float32(tau)) / np.float32(tau)
    _, H, W = costs.shape
    cx, cy = (W - 1) / 2, (H - 1) / 2
    checked = 0
    for t in np.flatnonzero(np.isfinite(placed.cost[:, 0])):
        f, u, v = placed.focal[t, 0], placed.u[t, 0], placed.v[t, 0]
        first, last = templates.offsets[t], templates.offsets[t + 1]
        rays = np.c_[templates.points[first:last].astype(np.float64), np.ones(last - first)]
        turned = rays @ turn_to(np.array([(u - cx) / f, (v - cy) / f, 1.0])).T
        x = np.floor(cx + f * turned[:, 0] / turned[:, 2] + 0.5).astype(int)
        y = np.floor(cy + f * turned[:, 1] / turned[:, 2] + 0.5).astype(int)
        inside = (x >= 0) & (y >= 0) & (x < W) & (y < H)
        checked += int((~inside).any())
        expected = costs[templates.bins[first:last][inside], y[inside], x[inside]].astype(np.float64).mean()
        assert abs(placed.cost[t, 0] - expected) < 1e-9
    assert checked > 0  # some best placements were cut by the frame


def test_only_the_allowed_templates_are_tried(sedan, renderer, templates):
    photo, _ = _photo(sedan, renderer, 4, templates, 260.0, 160.0, 120.0)
    edges = photo_edges(photo)
    allowed = np.zeros(len(templates), bool)
    allowed[[0, 6]] = True
    placed = match(templates, edges.distance, 20.0, [(0.0, 0.0, 319.0, 239.0)], allowed=allowed, min_iou=0.2)
    assert np.isfinite(placed.cost[[0, 6], 0]).all() and np.isinf(np.delete(placed.cost[:, 0], [0, 6])).all()
    with pytest.raises(ValueError, match="target box"):
        match(templates, edges.distance, 20.0, [])


def test_templates_are_kept_with_the_prepared_model(sedan, renderer, tmp_path):
    store = ModelStore(tmp_path)
    path = sedan.info.mesh_path
    first = model_from_mesh(path, up=sedan.info.up, forward=sedan.info.forward, store=store)
    made = first.templates(renderer, GRID)
    again = model_from_mesh(path, up=sedan.info.up, forward=sedan.info.forward, store=store)
    read = again.templates(renderer, GRID)
    for name, a in made.arrays().items():
        assert np.array_equal(a, read.arrays()[name]), name
    manifest = next(tmp_path.glob("*/manifest.json")).read_text()
    assert '"templates"' in manifest
