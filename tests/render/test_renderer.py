"""The EGL renderer: exact coverage, camera-facing normals, textures, robustness to bad geometry."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from vehicle_pose.geometry.camera import Camera, look_at_camera
from vehicle_pose.render.layers import supported
from vehicle_pose.render.renderer import Frame, Renderer

from helpers import mesh_from_trimesh

K = np.array([[300.0, 0.0, 159.5], [0.0, 300.0, 119.5], [0.0, 0.0, 1.0]])


def _box_camera(azimuth: float, elevation: float) -> Camera:
    return look_at_camera([0, 0, 0], [1, 0, 0], [0, 0, 1], azimuth_deg=azimuth, elevation_deg=elevation,
                          distance=6.0, focal=300.0, width=320, height=240)


def _projected_box_mask(box: trimesh.Trimesh, cam: Camera) -> np.ndarray:
    """Pixels whose centre lies inside the convex hull of the box's projected corners."""
    import cv2

    uv = cam.project(box.vertices)
    hull = cv2.convexHull(uv.astype(np.float32))
    ys, xs = np.mgrid[0 : cam.height, 0 : cam.width]
    pts = np.column_stack([xs.ravel(), ys.ravel()]).astype(np.float32)
    inside = np.array([cv2.pointPolygonTest(hull, (float(x), float(y)), False) >= 0 for x, y in pts])
    return inside.reshape(cam.height, cam.width)


@pytest.mark.parametrize("azimuth,elevation", [(30, 20), (120, 35), (200, 10), (300, 50)])
def test_box_coverage_matches_vertex_projection(renderer, azimuth, elevation):
    box = trimesh.creation.box(extents=(2.0, 1.2, 0.8))
    cam = _box_camera(azimuth, elevation)
    frame = renderer.render(mesh_from_trimesh(box), cam)
    truth = _projected_box_mask(box, cam)
    cov = frame.coverage
    iou = (cov & truth).sum() / (cov | truth).sum()
    assert iou > 0.99


def test_normals_face_the_camera_and_are_unit(renderer):
    sphere = trimesh.creation.icosphere(subdivisions=3)
    cam = _box_camera(45, 20)
    frame = renderer.render(mesh_from_trimesh(sphere), cam)
    n = frame.covered(frame.attrs)[:, 1:]
    assert frame.pixel_count > 1000
    assert np.all(np.linalg.norm(n, axis=1) == pytest.approx(1.0, abs=1e-3))
    # In OpenCV camera coordinates the camera looks along +z: visible normals have n_z < 0.
    assert np.all(n[:, 2] < 0.05)
    assert np.mean(n[:, 2] < 0) > 0.99


def test_flipped_faces_give_the_same_normals(renderer):
    sphere = trimesh.creation.icosphere(subdivisions=3)
    flipped = sphere.copy()
    faces = flipped.faces.copy()
    faces[::2] = faces[::2, ::-1]
    flipped = trimesh.Trimesh(flipped.vertices, faces, process=False)
    assert not flipped.is_winding_consistent
    from vehicle_pose.model.loading import shading_geometry
    from vehicle_pose.model.mesh import Mesh, Part

    verts, normals, tris = shading_geometry(flipped)
    bad = Mesh((Part("p", "body", verts, normals, tris, np.ones(len(verts), np.float32)),))
    cam = _box_camera(45, 20)
    good = renderer.render(mesh_from_trimesh(sphere), cam)
    got = renderer.render(bad, cam)
    assert np.array_equal(got.labels > 0, good.labels > 0)
    dot = (got.covered(got.attrs)[:, 1:] * good.covered(good.attrs)[:, 1:]).sum(1)
    assert np.median(dot) > 0.99


def test_off_screen_and_behind_camera_give_empty_frames(renderer):
    box = mesh_from_trimesh(trimesh.creation.box(extents=(1, 1, 1)))
    behind = Camera(K, np.eye(3), np.array([0.0, 0.0, -5.0]), 320, 240)
    aside = Camera(K, np.eye(3), np.array([50.0, 0.0, 5.0]), 320, 240)
    for cam in (behind, aside):
        assert renderer.render(box, cam).pixel_count == 0


def test_camera_inside_the_bounding_sphere_clips_instead_of_failing(renderer):
    box = mesh_from_trimesh(trimesh.creation.box(extents=(4, 4, 4)))
    cam = Camera(K, np.eye(3), np.array([0.0, 0.0, 1.5]), 320, 240)
    frame = renderer.render(box, cam)
    assert frame.pixel_count > 0.9 * 320 * 240


def test_many_image_sizes_in_turn_render_without_error(renderer):
    """The renderer keeps a few framebuffers; replacing them must not break the bound one."""
    box = mesh_from_trimesh(trimesh.creation.box(extents=(1, 1, 1)))
    cam = _box_camera(30, 20)
    counts = {}
    for w, h in [(320, 240), (160, 120), (200, 150), (100, 75), (452, 339), (320, 240), (90, 70), (452, 339)]:
        counts[(w, h)] = renderer.render(box, cam.scaled(w, h)).pixel_count
        assert counts[(w, h)] > 0
    assert counts[(320, 240)] == renderer.render(box, cam).pixel_count


def test_framebuffers_replaced_free_their_memory():
    """Sixty image sizes in turn (photos of every size, a worker's day): the framebuffers let go
    take their renderbuffers with them. Each 600x600 one holds about 8.6 MB; four are kept."""
    import os

    def resident() -> float:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6

    renderer = Renderer()
    try:
        for i in range(8):  # the allocator's first growth
            renderer.framebuffer(600 + i, 600)
        before = resident()
        for i in range(60):
            renderer.framebuffer(620 + i, 600)
        assert resident() - before < 100.0  # 500 MB when the renderbuffers were kept
    finally:
        renderer.release()


def test_frame_indices_address_the_whole_image():
    labels = np.zeros((3, 4), np.uint8)
    labels[1, 2] = 1
    frame = Frame(np.zeros((3, 4, 4), np.float32), labels, 5, 6, 20, 10)
    assert frame.covered_flat_indices().tolist() == [(6 + 1) * 20 + 5 + 2]
    assert frame.coverage[7, 7]


def test_textured_parts_modulate_albedo(renderer, tmp_path):
    from PIL import Image

    from vehicle_pose.model.loading import load_mesh

    quad = trimesh.Trimesh([[0, -1, -1], [0, 1, -1], [0, 1, 1], [0, -1, 1]], [[0, 1, 2], [0, 2, 3]], process=False)
    tex = np.zeros((8, 8, 3), np.uint8)
    tex[:, 4:] = 255
    quad.visual = trimesh.visual.TextureVisuals(uv=[[0, 0], [1, 0], [1, 1], [0, 1]], image=Image.fromarray(tex))
    path = tmp_path / "quad.glb"
    quad.export(path)
    mesh = load_mesh(path)
    assert mesh.parts[0].texture is not None
    cam = look_at_camera([0, 0, 0], [1, 0, 0], [0, 0, 1], azimuth_deg=0, elevation_deg=0, distance=4.0,
                         focal=200.0, width=160, height=120)
    frame = renderer.render(mesh, cam)
    k = frame.covered(frame.attrs)[:, 0]
    assert k.max() > 0.3 and k.min() < 0.05 * k.max()


@pytest.mark.parametrize("suffix", [".obj", ".glb"])
def test_textures_are_not_upside_down(renderer, tmp_path, suffix):
    # The upper half of the image is white, the lower black; the quad's top edge has v = 1,
    # which is the image's top in every format trimesh reads (OBJ and glTF alike).
    from PIL import Image

    from vehicle_pose.model.loading import load_mesh

    quad = trimesh.Trimesh([[0, -1, -1], [0, 1, -1], [0, 1, 1], [0, -1, 1]], [[0, 1, 2], [0, 2, 3]], process=False)
    tex = np.zeros((16, 16, 3), np.uint8)
    tex[:8] = 255
    quad.visual = trimesh.visual.TextureVisuals(uv=[[0, 0], [1, 0], [1, 1], [0, 1]], image=Image.fromarray(tex))
    path = tmp_path / f"quad{suffix}"
    quad.export(path)
    mesh = load_mesh(path, texture_dirs=[tmp_path])
    assert mesh.parts[0].texture is not None
    cam = look_at_camera([0, 0, 0], [1, 0, 0], [0, 0, 1], azimuth_deg=0, elevation_deg=0, distance=4.0,
                         focal=200.0, width=160, height=120)
    frame = renderer.render(mesh, cam)
    k = frame.full(frame.attrs[..., 0])
    cov = frame.coverage
    rows = np.flatnonzero(cov.any(axis=1))
    # Medians: the texture repeats, so the outermost texels blend with the opposite edge.
    top, bottom = (float(np.median(k[r][cov[r]])) for r in (rows[:10], rows[-10:]))
    assert top > 0.3 and bottom < 0.1 * top, (top, bottom)


def test_parts_with_textures_of_different_sizes_keep_their_own(renderer):
    # Three quads side by side in one mesh, drawn in one call: a 4x4 texture dark on its left
    # half, a 16x16 one dark on its lower half (one texture array, the smaller layer resized),
    # and an untextured part; each shows its own pattern, as when rendered alone.
    from vehicle_pose.model.mesh import Mesh, Part

    def quad(y, tex, label):
        verts = np.array([[0, y - 0.45, -0.45], [0, y + 0.45, -0.45], [0, y + 0.45, 0.45], [0, y - 0.45, 0.45]])
        uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
        return Part(label, "body", verts, np.tile([[1.0, 0, 0]], (4, 1)).astype(np.float32),
                    np.array([[0, 1, 2], [0, 2, 3]], np.uint32), np.full(4, 0.8, np.float32),
                    uv if tex is not None else None, tex)

    small = np.full((4, 4, 3), 255, np.uint8)
    small[:, :2] = 0
    large = np.full((16, 16, 3), 255, np.uint8)
    large[8:] = 0  # image rows 8-15: the lower half (v < 0.5)
    parts = (quad(-1.0, small, "a"), quad(0.0, large, "b"), quad(1.0, None, "c"))
    cam = look_at_camera([0, 0, 0], [1, 0, 0], [0, 0, 1], azimuth_deg=0, elevation_deg=0, distance=4.0,
                         focal=150.0, width=200, height=120)
    together = renderer.render(Mesh(parts), cam)
    k = together.full(together.attrs[..., 0])
    for part in parts:
        alone = renderer.render(Mesh((part,)), cam)
        cov = alone.coverage
        assert (together.coverage & cov).sum() == cov.sum()
        ka = alone.full(alone.attrs[..., 0])
        assert np.median(np.abs(k[cov] - ka[cov])) < 1e-3
        ys, xs = np.nonzero(cov)
        x0, x1, y0, y1 = xs.min(), xs.max(), ys.min(), ys.max()
        qx, qy = (x1 - x0) // 4, (y1 - y0) // 4
        left, right = np.median(k[y0:y1, x0:x0 + qx]), np.median(k[y0:y1, x1 - qx:x1])
        top, bottom = np.median(k[y0:y0 + qy, x0:x1]), np.median(k[y1 - qy:y1, x0:x1])
        if part.name == "a":
            assert right > 0.7 and left < 0.02, (left, right)
        elif part.name == "b":
            assert top > 0.7 and bottom < 0.02, (top, bottom)
        else:
            assert min(left, right, top, bottom) == pytest.approx(0.8, abs=1e-6)


def test_degenerate_triangles_give_finite_attributes(renderer):
    verts = np.array([[0, -1, -1], [0, 1, -1], [0, 1, 1], [0, -1, 1], [0, 0, 0], [0, 0, 0]], np.float64)
    faces = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 5]], np.uint32)
    from vehicle_pose.model.mesh import Mesh, Part

    mesh = Mesh((Part("p", "body", verts, np.zeros((6, 3), np.float32), faces, np.ones(6, np.float32)),))
    cam = look_at_camera([0, 0, 0], [1, 0, 0], [0, 0, 1], azimuth_deg=0, elevation_deg=0, distance=4.0,
                         focal=200.0, width=160, height=120)
    frame = renderer.render(mesh, cam)
    assert frame.pixel_count > 100 and np.all(np.isfinite(frame.attrs))


def _about(model_mesh, count: int, width: int = 320, height: int = 240, seed: int = 0) -> list[Camera]:
    """Cameras looking at a mesh from random directions and distances, some cut by the frame."""
    rng = np.random.default_rng(seed)
    centre, radius = model_mesh.sphere
    cams = []
    for _ in range(count):
        cam = look_at_camera(centre, [1, 0, 0], [0, 0, 1], azimuth_deg=float(rng.uniform(0, 360)),
                             elevation_deg=float(rng.uniform(-10, 60)), distance=float(rng.uniform(2.0, 6.0)) * radius,
                             focal=float(rng.uniform(200, 500)), width=width, height=height)
        K = cam.K.copy()
        K[:2, 2] += rng.uniform(-80, 80, 2)  # the car off-centre, at times partly out of the frame
        cams.append(Camera(K, cam.R, cam.t, width, height))
    return cams


def _same(a: Frame, b: Frame) -> bool:
    return (a.x0, a.y0, a.labels.shape) == (b.x0, b.y0, b.labels.shape) and np.array_equal(a.labels, b.labels) \
        and np.array_equal(a.covered(a.attrs), b.covered(b.attrs))


def test_poses_drawn_together_equal_each_drawn_alone_bit_for_bit(renderer, sedan):
    """``render_many`` draws a population in layers of one draw call (where the context can,
    as llvmpipe and NVIDIA's drivers can): every frame is the single draw's, empty ones too."""
    mesh = sedan.exterior(4096, renderer)
    cams = _about(mesh, 150)  # more than one draw's layers
    cams[7] = Camera(K, np.eye(3), np.array([0.0, 0.0, -50.0]), 320, 240)  # behind the camera
    cams[40] = Camera(K, np.eye(3), np.array([500.0, 0.0, 5.0]), 320, 240)  # off-screen
    together = renderer.render_many(mesh, cams)
    assert renderer.draws_layers == supported(renderer.ctx)  # llvmpipe and NVIDIA's drivers can
    assert len(together) == len(cams)
    assert together[7].pixel_count == together[40].pixel_count == 0
    assert sum(f.pixel_count > 0 for f in together) > 140
    assert all(_same(renderer.render(mesh, cam), frame) for cam, frame in zip(cams, together, strict=True))


def test_generations_of_several_sizes_in_turn_equal_single_draws(renderer, sedan):
    """Each draw clears only the layers it uses: a generation of 9 after one of 100 (and of 30
    after it) finds nothing of the poses before it in its frames."""
    mesh = sedan.exterior(4096, renderer)
    for k, count in enumerate((100, 9, 30, 9)):
        cams = _about(mesh, count, seed=k)
        together = renderer.render_many(mesh, cams)
        assert all(_same(renderer.render(mesh, cam), frame) for cam, frame in zip(cams, together, strict=True))


def test_poses_drawn_together_keep_their_textures(renderer, tmp_path):
    from PIL import Image

    from vehicle_pose.model.loading import load_mesh

    quad = trimesh.Trimesh([[0, -1, -1], [0, 1, -1], [0, 1, 1], [0, -1, 1]], [[0, 1, 2], [0, 2, 3]], process=False)
    tex = np.zeros((8, 8, 3), np.uint8)
    tex[:, 4:] = 255
    quad.visual = trimesh.visual.TextureVisuals(uv=[[0, 0], [1, 0], [1, 1], [0, 1]], image=Image.fromarray(tex))
    quad.export(tmp_path / "quad.glb")
    mesh = load_mesh(tmp_path / "quad.glb")
    cams = [look_at_camera([0, 0, 0], [1, 0, 0], [0, 0, 1], azimuth_deg=a, elevation_deg=e, distance=4.0,
                           focal=200.0, width=160, height=120) for a in (-30, 0, 25) for e in (-20, 0, 30)]
    together = renderer.render_many(mesh, cams)
    assert all(_same(renderer.render(mesh, cam), frame) for cam, frame in zip(cams, together, strict=True))
    k = together[4].covered(together[4].attrs)[:, 0]
    assert k.max() > 0.3 and k.min() < 0.05 * k.max()


def test_poses_of_many_sizes_drawn_together_and_alone_in_turn(renderer, sedan):
    """Cameras of different sizes are drawn one at a time; the layered targets of several sizes
    in turn (two are kept, the others let go) leave the single draws' framebuffers working."""
    mesh = sedan.exterior(4096, renderer)
    mixed = _about(mesh, 3) + _about(mesh, 3, 200, 150)
    together = renderer.render_many(mesh, mixed)
    assert all(_same(renderer.render(mesh, c), f) for c, f in zip(mixed, together, strict=True))
    for w, h in [(320, 240), (160, 120), (200, 150), (320, 240), (90, 70), (452, 339)]:
        cams = _about(mesh, 5, w, h, seed=w)
        together = renderer.render_many(mesh, cams)
        assert all(_same(renderer.render(mesh, c), f) for c, f in zip(cams, together, strict=True))
    assert len(renderer._targets) <= 2


def _drawn_one_at_a_time(ctx, sedan) -> None:
    """A fresh renderer on ``ctx`` draws a population one pose at a time, each frame the
    single draw's, holding no layered target and leaving no error on the context."""
    renderer = Renderer(ctx)
    try:
        mesh = sedan.exterior(4096, renderer)
        cams = _about(mesh, 5)
        assert all(_same(renderer.render(mesh, c), f) for c, f in zip(cams, renderer.render_many(mesh, cams),
                                                                      strict=True))
        assert not renderer.draws_layers and not renderer._targets
        assert ctx.error == "GL_NO_ERROR"
    finally:
        renderer.release()


def test_a_context_without_layered_draws_draws_poses_one_at_a_time(ctx, sedan, monkeypatch):
    import vehicle_pose.render.renderer as rendering

    monkeypatch.setattr(rendering, "supported", lambda _ctx: False)
    _drawn_one_at_a_time(ctx, sedan)


def test_a_renderer_that_drew_layers_releases_them(ctx, sedan):
    renderer = Renderer(ctx)
    mesh = sedan.exterior(4096, renderer)
    assert renderer.render_many(mesh, _about(mesh, 4))[0].pixel_count > 0
    assert bool(renderer._targets) == supported(ctx)
    renderer.release()
    assert not renderer._targets and ctx.error == "GL_NO_ERROR"
    assert Renderer(ctx).render(mesh, _about(mesh, 1)[0]).pixel_count > 0


def test_a_driver_that_will_not_clear_layers_draws_poses_one_at_a_time(ctx, sedan, monkeypatch):
    """A layered target whose clear records an OpenGL error (here a clear of texture 0, which
    no driver accepts) is given up when made: the renderer draws one pose at a time, and no
    error is left on the context."""
    from vehicle_pose.render import layers

    calls = layers._calls()
    if calls is None or not supported(ctx):
        pytest.skip("the context draws no layers")
    real = calls.glClearTexSubImage
    monkeypatch.setattr(calls, "glClearTexSubImage", lambda texture, *args: real(0, *args))
    _drawn_one_at_a_time(ctx, sedan)


def test_a_driver_that_will_not_make_layered_targets_draws_poses_one_at_a_time(ctx, sedan, monkeypatch):
    import vehicle_pose.render.renderer as rendering
    from vehicle_pose.errors import RenderError

    def refuse(*args, **kwargs):
        raise RenderError("the layered framebuffer is incomplete")

    monkeypatch.setattr(rendering, "LayeredTarget", type("Refused", (), {"__init__": refuse,
                                                                         "nbytes": rendering.LayeredTarget.nbytes}))
    _drawn_one_at_a_time(ctx, sedan)
