"""The sparse contour model: edge points put back on the surface, projected without a render."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vehicle_pose.geometry.camera import Camera
from vehicle_pose.loss.edges import EdgeLoss, model_edges
from vehicle_pose.render.synth import LIGHTINGS, synthesize
from vehicle_pose.search.contours import ContourGrid, ContourModel, contour_model

from helpers import perturbed, view


def _rendered_edges(renderer, mesh, camera: Camera) -> np.ndarray:
    """(H, W) int8: the rendered model's edge bins over the whole image, -1 off the edges."""
    frame = renderer.render(mesh, camera)
    edges = model_edges(frame)
    out = np.full((camera.height, camera.width), -1, np.int8)
    out[frame.y0:frame.y0 + edges.shape[0], frame.x0:frame.x0 + edges.shape[1]] = edges
    return out


@pytest.mark.parametrize("azimuth,elevation,distance", [(130.0, 12.0, 9.0), (47.0, 3.0, 6.0), (250.0, 27.0, 25.0)])
def test_the_projected_points_lie_on_the_rendered_edges_with_their_orientation(sedan, renderer, azimuth, elevation,
                                                                             distance):
    """Off the grid's views (the nearest view's points), at the structure's 320 pixels: the
    points lie within a pixel of a rendered edge and most have its orientation bin."""
    camera = view(sedan, azimuth, elevation, distance=distance, focal=450.0 * distance / 9.0, width=320, height=240)
    contours = contour_model(sedan, 8192, renderer)
    edges = _rendered_edges(renderer, sedan.exterior(8192, renderer), camera)
    distance_px = cv2.distanceTransform((edges < 0).astype(np.uint8), cv2.DIST_L2, 3)
    uv, bins = contours.project(camera, renderer)
    inside = np.all((uv >= 0) & (uv < [319.5, 239.5]), axis=1)
    assert inside.sum() > 200
    px = np.floor(uv[inside] + 0.5).astype(int)
    assert np.percentile(distance_px[px[:, 1], px[:, 0]], 90) <= 1.0
    on = edges[px[:, 1], px[:, 0]]
    mine = bins[inside][on >= 0]
    theirs = on[on >= 0].astype(int)
    apart = np.minimum((mine - theirs) % 8, (theirs - mine) % 8)
    assert np.mean(apart <= 1) > 0.7


def test_the_view_depends_on_the_cameras_position_and_the_scale_on_its_focal_length(sedan, renderer):
    """A camera placed at a grid view picks it, at the scale nearest the size it sees the model
    at; turning the camera about its own centre or moving its principal point keeps both, a
    longer lens keeps the view and takes a larger scale."""
    contours = contour_model(sedan, 8192, renderer)
    grid = contours.grid
    radius = sedan.mesh.sphere[1]
    azimuth, elevation = 3 * grid.azimuth_step, grid.elevations[0] + 4 * grid.elevation_step
    distance, focal = grid.distances[2] * radius, grid.scales[1] * grid.distances[2]
    camera = view(sedan, azimuth, elevation, distance=distance, focal=focal)
    at = (2, 4, 3, 1)
    assert contours.view(camera) == at
    turn = cv2.Rodrigues(np.radians([4.0, -7.0, 10.0]))[0]
    R = turn @ camera.R
    K = camera.K.copy()
    K[:2, 2] += [40.0, -25.0]
    moved = Camera(K, R, -R @ camera.eye, camera.width, camera.height)
    np.testing.assert_allclose(moved.eye, camera.eye, atol=1e-9)
    assert contours.view(moved) == at
    K[:2, :2] *= grid.scales[2] / grid.scales[1]
    longer = Camera(K, R, -R @ camera.eye, camera.width, camera.height)
    assert contours.view(longer) == (*at[:3], 2)
    aside = view(sedan, azimuth + 2 * grid.azimuth_step, elevation, distance=distance, focal=focal)
    assert contours.view(aside) == (2, 4, 5, 1)


def test_a_views_points_are_the_same_in_every_process(sedan, renderer):
    """Each view's sample of edge pixels is seeded by the view: drawn again, the same points."""
    one = contour_model(sedan, 8192, renderer)
    other = ContourModel(sedan, sedan.exterior(8192, renderer), ContourGrid())
    key = (2, 5, 20, 3)
    drawn = other.drawn
    p, q = one.points(key, renderer)
    np.testing.assert_array_equal(other.points(key, renderer)[0], p)
    np.testing.assert_array_equal(other.points(key, renderer)[1], q)
    assert other.drawn == drawn + 1 and 0 < len(p) <= ContourGrid().points


def test_the_sparse_cost_follows_the_rendered_chamfer(sedan, renderer):
    """On a synthetic photo, the chamfer of poses 1-13 degrees off the truth: the sparse
    model's cost follows the rendered one (the structure's searches rank poses by it), and the
    truth costs least."""
    truth = view(sedan, 130.0, 12.0, focal=450.0, width=320, height=240)
    photo, _ = synthesize(sedan.mesh, truth, lighting=LIGHTINGS["side"], renderer=renderer, seed=5)
    loss = EdgeLoss(photo, tau=0.03)
    mesh = sedan.exterior(8192, renderer)
    contours = contour_model(sedan, 8192, renderer)
    cameras = [truth] + [perturbed(truth, s, degrees=1.0 + 0.4 * s, shift=0.01 + 0.002 * s, focal=0.05)
                         for s in range(30)]
    rendered = np.array([loss(renderer.render(mesh, c)) for c in cameras])
    sparse = np.array([contours.cost(c, loss.edges.distance, loss.tau, renderer) for c in cameras])
    assert np.corrcoef(rendered, sparse)[0, 1] > 0.97
    assert np.mean(np.abs(rendered - sparse)) < 0.03
    assert sparse[0] < sparse[1:].min()


def test_a_pose_that_puts_the_points_out_of_the_frame_costs_one(sedan, renderer):
    truth = view(sedan, 130.0, 12.0, focal=450.0, width=320, height=240)
    photo, _ = synthesize(sedan.mesh, truth, renderer=renderer, seed=1)
    loss = EdgeLoss(photo, tau=0.03)
    aside = Camera(truth.K, truth.R, truth.t + np.array([40.0, 0.0, 0.0]), 320, 240)  # the model far to the left
    assert contour_model(sedan, 8192, renderer).cost(aside, loss.edges.distance, loss.tau, renderer) == 1.0


def test_only_the_views_last_used_are_kept(sedan, renderer):
    contours = ContourModel(sedan, sedan.exterior(8192, renderer), ContourGrid(kept=2))
    first = contours.points((3, 4, 0, 3), renderer)
    contours.points((3, 4, 1, 3), renderer)
    assert contours.points((3, 4, 0, 3), renderer) is first  # used again: kept, now the latest
    contours.points((3, 4, 2, 3), renderer)  # the view 1 goes
    assert contours.drawn == 2
    assert contours.points((3, 4, 0, 3), renderer) is first
