"""The exterior pass: hidden faces dropped, one-sided faces oriented, the same pixels rendered."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from vehicle_pose.geometry.camera import look_at_camera
from vehicle_pose.render.exterior import exterior_faces

from helpers import mesh_from_trimesh


def _assert_renders_the_same(renderer, a, b, views, *, distance=5.0, focal=250.0, centre=(0, 0, 0)):
    for azimuth, elevation in views:
        cam = look_at_camera(centre, [1, 0, 0], [0, 0, 1], azimuth_deg=azimuth, elevation_deg=elevation,
                             distance=distance, focal=focal, width=320, height=240)
        fa, fb = renderer.render(a, cam), renderer.render(b, cam)
        assert fa.pixel_count > 0
        np.testing.assert_array_equal(fa.labels, fb.labels)
        # Reversed winding interpolates in another order (differences of 1e-5); where a near
        # and a far face tie in depth along an outline, drawing both sides may show the far
        # one, culling shows the near one: a few pixels.
        off = (np.abs(fa.attrs - fb.attrs).max(axis=-1) > 1e-4) & (fa.labels > 0)
        assert off.sum() <= 0.005 * fa.pixel_count, f"{off.sum()} of {fa.pixel_count} pixels differ"


_VIEWS = [(0, 5), (75, 30), (160, -20), (250, 60), (330, 15), (45, -70), (110, 89)]


def test_exterior_drops_hidden_faces_and_renders_the_same(renderer):
    # A closed box with a smaller box inside it (a car's cabin inside its body shell) and a
    # sphere outside it: the inner box's 12 faces are never seen from outside.
    outer = trimesh.creation.box(extents=(4.0, 1.8, 1.4))
    inner = trimesh.creation.box(extents=(2.0, 1.0, 0.8))
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.4)
    ball.apply_translation([2.6, 0.0, 0.0])
    mesh = mesh_from_trimesh(trimesh.util.concatenate([outer, inner, ball]))
    # 12 hidden faces of 344 are too few to be worth dropping by default (min_hidden=0.05):
    # they are kept, drawn from both sides; every other face is seen from outside only.
    kept = exterior_faces(renderer, mesh)
    assert kept.n_faces == mesh.n_faces
    assert sum(len(p.faces) for p in kept.parts if not p.one_sided) == len(inner.faces)
    ext = exterior_faces(renderer, mesh, min_hidden=0.0)
    assert ext.n_faces == mesh.n_faces - len(inner.faces)
    assert all(p.one_sided for p in ext.parts)
    assert exterior_faces(renderer, mesh, min_hidden=0.0) is ext  # cached per mesh and arguments
    corners = np.concatenate([p.vertices[p.faces].reshape(-1, 3) for p in ext.parts])
    assert np.abs(corners).max(axis=0)[1] > 0.85  # the outer box and the sphere remain
    assert not np.any(np.all(np.abs(corners) < [1.01, 0.51, 0.41], axis=1)), "an inner-box face was kept"
    _assert_renders_the_same(renderer, mesh, kept, _VIEWS)
    _assert_renders_the_same(renderer, mesh, ext, _VIEWS)


def test_exterior_drops_a_large_hidden_part_by_default(renderer):
    engine = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    mesh = mesh_from_trimesh(trimesh.util.concatenate([trimesh.creation.box(extents=(4.0, 1.8, 1.4)), engine]))
    assert exterior_faces(renderer, mesh).n_faces == 12


def test_exterior_orients_inconsistent_winding_for_culling(renderer):
    # Internet CAD: a closed surface with the winding of a random half of its faces reversed.
    # Every face is seen from one side only; after orientation, culling what faces away from
    # the camera draws exactly what drawing both sides does, from far and from close.
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    faces = sphere.faces.copy()
    flip = np.random.default_rng(3).random(len(faces)) < 0.5
    faces[flip] = faces[flip][:, ::-1]
    mesh = mesh_from_trimesh(trimesh.Trimesh(sphere.vertices * [2.0, 0.9, 0.7], faces, process=False))
    ext = exterior_faces(renderer, mesh)
    assert ext.n_faces == mesh.n_faces and all(p.one_sided for p in ext.parts)
    _assert_renders_the_same(renderer, mesh, ext, _VIEWS)
    _assert_renders_the_same(renderer, mesh, ext, _VIEWS[:4], distance=2.6, focal=120.0)


def test_exterior_keeps_a_thin_sheet_two_sided(renderer):
    # A closed body with a single-sheet fin (a spoiler, a mirror): the fin is seen from both
    # sides and must never be culled; the body is.
    body = trimesh.creation.box(extents=(4.0, 1.8, 1.4))
    fin = trimesh.Trimesh([[1.0, 0.0, 0.7], [2.0, 0.0, 0.7], [2.0, 0.0, 1.5], [1.0, 0.0, 1.5]],
                          [[0, 1, 2], [0, 2, 3]], process=False)
    mesh = mesh_from_trimesh(trimesh.util.concatenate([body, fin]))
    ext = exterior_faces(renderer, mesh)
    assert sum(len(p.faces) for p in ext.parts if p.one_sided) == len(body.faces)
    assert sum(len(p.faces) for p in ext.parts if not p.one_sided) == len(fin.faces)
    # Views of either side of the fin.
    _assert_renders_the_same(renderer, mesh, ext, [(90, 10), (270, 10), (60, 40), (240, 40)])


def test_lanes_and_skipped_slivers_count_the_pixels_one_full_draw_counts(renderer, sedan):
    """On a software rasteriser the pass leaves out the faces no pixel centre can fall in and
    draws its views in several contexts at once: each face's pixel counts must be those of
    every face drawn in one context. A dense sheet of slivers (the sedan's body subdivided
    twice: most faces under a pixel) and the sedan's own parts."""
    from vehicle_pose.render import exterior as ex

    if not ex._software(renderer) or ex._gl_functions() is None:
        pytest.skip("the lanes and the face choice are for Mesa's CPU rasteriser")
    body = max(sedan.mesh.parts, key=lambda p: len(p.faces))
    v, f = body.vertices, body.faces
    for _ in range(2):
        v, f = trimesh.remesh.subdivide(v, f)
    dense = mesh_from_trimesh(trimesh.Trimesh(v, f, process=False))
    for mesh in (dense, sedan.mesh):
        offsets = np.cumsum([0] + [len(p.vertices) for p in mesh.parts])
        points = np.concatenate([p.vertices for p in mesh.parts]).astype(np.float32)
        faces = np.concatenate([p.faces.astype(np.int64) + o for p, o in zip(mesh.parts, offsets[:-1], strict=True)])
        soup = np.ascontiguousarray(points[faces])
        views = ex._view_matrices(mesh, ex.sphere_directions(6), 2.0)
        work = (points, faces, soup, 256, True, ex._gl_functions())
        full = ex._count_views(renderer, views, points, faces, soup, 256, False, None)
        one_lane = ex._count_views(renderer, views, *work)
        helper = ex._helper_pool().submit(ex._helper_lane, views[1::2], work)
        main = ex._count_views(renderer, views[::2], *work)
        other = helper.result()
        for side in (0, 1):
            np.testing.assert_array_equal(one_lane[side], full[side])
            np.testing.assert_array_equal(main[side] + other[side], full[side])
        assert full[0][1:].sum() > 0 and (full[0][1:] + full[1][1:] == 0).any()
    index = np.empty(3 * len(faces), np.int32)
    kept = ex._compiled_sampled_faces()(points, faces, views[0], 256, index)
    assert kept < len(faces)  # some faces of the sedan are left out of a 256 pixel view


def test_exterior_pass_is_the_same_in_lanes_and_in_one(renderer, sedan, monkeypatch):
    from vehicle_pose.render import exterior as ex

    if not ex._software(renderer) or ex._gl_functions() is None:
        pytest.skip("the lanes are for Mesa's CPU rasteriser")
    mesh = sedan.mesh.decimated(4000)
    monkeypatch.setattr(ex, "_lanes", lambda: 1)
    one = ex.exterior_faces(renderer, mesh, directions=8, size=128)
    monkeypatch.setattr(ex, "_lanes", lambda: 3)
    ex._EXTERIOR.clear()
    three = ex.exterior_faces(renderer, mesh, directions=8, size=128)
    assert one is not three
    for p, q in zip(one.parts, three.parts, strict=True):
        assert p.one_sided == q.one_sided
        np.testing.assert_array_equal(p.faces, q.faces)


def test_a_lane_without_a_context_is_drawn_by_the_main_one(renderer, sedan, monkeypatch, caplog):
    from vehicle_pose.errors import RenderError
    from vehicle_pose.render import exterior as ex

    if not ex._software(renderer) or ex._gl_functions() is None:
        pytest.skip("the lanes are for Mesa's CPU rasteriser")
    mesh = sedan.mesh.decimated(3000)
    monkeypatch.setattr(ex, "_lanes", lambda: 1)
    one = ex.exterior_faces(renderer, mesh, directions=6, size=96)

    def no_context(views, work):
        raise RenderError("cannot create a headless OpenGL context (egl): test")

    monkeypatch.setattr(ex, "_lanes", lambda: 2)
    monkeypatch.setattr(ex, "_helper_lane", no_context)
    ex._EXTERIOR.clear()
    again = ex.exterior_faces(renderer, mesh, directions=6, size=96)
    assert "drawing its views here" in caplog.text
    for p, q in zip(one.parts, again.parts, strict=True):
        np.testing.assert_array_equal(p.faces, q.faces)
