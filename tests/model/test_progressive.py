"""Levels of detail from one simplification: each the simplifier's own result, to the last bit.

The reference is fast-simplification run to each target; the meshes are the shipped sedan's
parts (closed shells and open sheets with borders), the same parts as a triangle soup merged back,
a subdivided body (many collapses per vertex) and a sheet with degenerate faces.
"""

from __future__ import annotations

import fast_simplification
import numpy as np
import pytest
import trimesh

from vehicle_pose.model.mesh import _fill_triangles
from vehicle_pose.model.progressive import Progressive


def _merged(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    tm = trimesh.Trimesh(vertices, faces, process=True)
    return np.asarray(tm.vertices, np.float64), np.asarray(tm.faces, np.int64)


def _same_as_the_simplifier(vertices: np.ndarray, faces: np.ndarray, fractions=(0.7, 0.3, 0.1, 0.02, 0.0)) -> None:
    progressive = Progressive(vertices, faces)
    for fraction in fractions:
        target = int(fraction * len(faces))
        points, tris, collapses = fast_simplification.simplify(vertices, faces, target_count=target,
                                                               return_collapses=True)
        got_points, got_tris = progressive.level(target)
        assert progressive.collapses_for(target) == len(collapses)
        np.testing.assert_array_equal(got_tris, tris)
        assert got_points.dtype == np.float64
        np.testing.assert_array_equal(got_points, points)  # bitwise, NaN where the simplifier has NaN


def _sedan_part(sedan, kind: str):
    return max((p for p in sedan.mesh.parts if p.kind == kind), key=lambda p: len(p.faces))


@pytest.mark.parametrize("kind", ["body", "glass", "tyre"])
def test_every_level_is_the_simplifiers_own_result(sedan, kind):
    part = _sedan_part(sedan, kind)
    _same_as_the_simplifier(*_merged(part.vertices, part.faces))


def test_a_subdivided_body_collapsed_many_times_over(sedan):
    part = _sedan_part(sedan, "body")
    v, f = _merged(part.vertices, part.faces)
    v, f = trimesh.remesh.subdivide(v, f)
    _same_as_the_simplifier(v, np.asarray(f, np.int64), fractions=(0.5, 0.05, 0.01))


def test_an_open_sheet_with_degenerate_faces():
    grid = np.stack(np.meshgrid(np.linspace(0, 1, 30), np.linspace(0, 1, 30)), -1).reshape(-1, 2)
    rng = np.random.default_rng(3)
    vertices = np.c_[grid, 0.05 * rng.standard_normal(len(grid))]
    i = np.arange(29)[:, None] * 30 + np.arange(29)[None, :]
    i = i.reshape(-1)
    faces = np.r_[np.c_[i, i + 1, i + 30], np.c_[i + 1, i + 31, i + 30]]
    vertices = np.r_[vertices, vertices[:5]]  # five faces of zero area (their normals are NaN)
    faces = np.r_[faces, np.c_[np.arange(5), np.arange(5) + 1, len(grid) + np.arange(5)]]
    _same_as_the_simplifier(vertices, faces.astype(np.int64))


def test_a_level_asks_no_more_collapses_than_the_run_made(sedan):
    part = _sedan_part(sedan, "body")
    progressive = Progressive(*_merged(part.vertices, part.faces))
    assert progressive.collapses_for(len(progressive.faces)) == 0
    assert progressive.collapses_for(0) == len(progressive.collapses)
    assert progressive.collapses_for(len(progressive.faces) - 1) == 1


def test_skipping_covered_triangles_draws_what_every_triangle_draws():
    import cv2

    rng = np.random.default_rng(5)
    shift, size = 4, 96
    centre = rng.uniform(-10, size + 10, (1500, 1, 2))  # some partly or wholly off the image
    tris = np.round((centre + rng.normal(0, 3, (1500, 3, 2))) * (1 << shift)).astype(np.int32)
    every = np.zeros((size, size), np.uint8)
    for t in tris:
        cv2.fillConvexPoly(every, t, 1, cv2.LINE_8, shift)
    skipped = np.zeros((size, size), np.uint8)
    _fill_triangles(skipped, tris, tris.min(axis=1), tris.max(axis=1), shift)
    np.testing.assert_array_equal(skipped, every)
    assert 0.3 < every.mean() < 1.0


def test_a_prepared_model_drops_its_simplification_records_and_can_still_make_a_level(sedan, renderer):
    from vehicle_pose.model.library import VehicleModel

    model = VehicleModel(sedan.info, sedan.mesh.decimated(8000))  # its own mesh: the fixture stays as it is
    first = model.mesh.decimated(4096)
    model.prepare(renderer, budgets=[4096])
    assert "_progressive_cache" not in model.mesh.__dict__
    again = model.mesh.decimated(4096)  # the simplifier runs again, to the same level
    for p, q in zip(first.parts, again.parts, strict=True):
        np.testing.assert_array_equal(p.vertices, q.vertices)
        np.testing.assert_array_equal(p.faces, q.faces)


def test_compiled_small_triangle_marks_are_the_array_passes():
    """The compiled pass of Mesh.outlines marks the corners of triangles under a pixel and
    lists the others, as the array operations it replaces did (corners off the image clipped)."""
    from vehicle_pose.model.mesh import _compiled_mark_small

    rng = np.random.default_rng(8)
    shift, size = 4, 64
    one = 1 << shift
    uv = rng.integers(-3 * one, (size + 3) * one, (400, 2)).astype(np.int32)
    uv[200:] = uv[:200] + rng.integers(-one, one, (200, 2))  # near twins: many small triangles
    faces = np.c_[rng.integers(0, 400, 3000), rng.integers(0, 400, 3000), rng.integers(0, 400, 3000)]
    faces[:1500, 1] = (faces[:1500, 0] + 200) % 400
    faces[:1500, 2] = faces[:1500, 1]
    c0, c1, c2 = uv[faces[:, 0]], uv[faces[:, 1]], uv[faces[:, 2]]
    lo, hi = np.minimum(np.minimum(c0, c1), c2), np.maximum(np.maximum(c0, c1), c2)
    small = np.maximum(hi[:, 0] - lo[:, 0], hi[:, 1] - lo[:, 1]) < one
    expected = np.zeros((size, size), np.uint8)
    px = np.clip(uv[np.unique(faces[small])] >> shift, 0, size - 1)
    expected[px[:, 1], px[:, 0]] = 1
    image = np.zeros((size, size), np.uint8)
    large = _compiled_mark_small()(uv, faces.astype(np.int64), image, shift)
    np.testing.assert_array_equal(image, expected)
    np.testing.assert_array_equal(large, np.flatnonzero(~small))
    assert 100 < small.sum() < 2900


def test_merged_vertices_are_trimeshs_processed_mesh(sedan):
    """merged_vertices gives the vertices and faces of trimesh's process=True: a soup merged back,
    vertices 1e-9 apart merged and 3e-8 apart kept, unused vertices dropped, first-seen order."""
    from vehicle_pose.model.progressive import merged_vertices

    rng = np.random.default_rng(2)
    part = _sedan_part(sedan, "body")
    soup_v, soup_f = part.vertices[part.faces.reshape(-1)], np.arange(3 * len(part.faces)).reshape(-1, 3)
    grid = rng.integers(0, 5, (300, 3)) * 0.25
    near = np.r_[grid, grid[:100] + 1e-9, grid[100:200] + 1e-7, grid[200:] + 3e-8, rng.normal(size=(50, 3))]
    near_f = rng.integers(0, len(near) - 20, (400, 3))  # the last 20 vertices unused
    for v, f in [(part.vertices, part.faces), (soup_v, soup_f), (near, near_f)]:
        tm = trimesh.Trimesh(v, f, process=True)
        mv, mf = merged_vertices(v, f)
        np.testing.assert_array_equal(mv, np.asarray(tm.vertices))
        np.testing.assert_array_equal(mf, np.asarray(tm.faces))
    assert len(merged_vertices(soup_v, soup_f)[0]) < len(soup_v) / 2
