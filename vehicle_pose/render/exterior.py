"""The exterior pass: the faces of a mesh that some view from outside sees.

Faces that no view from outside can see (the cabin, engine and inner shells that CAD models of
cars often carry) never reach a pixel, yet each costs as much as a visible face in the
rasteriser's set-up; :func:`exterior_faces` drops them and orients the faces seen from one side
only, so that the renderer can cull them from behind.
"""

from __future__ import annotations

import ctypes
import functools
import logging
import os
import threading
import weakref
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import moderngl
import numpy as np
import numpy.typing as npt

from vehicle_pose.errors import RenderError
from vehicle_pose.model.mesh import Mesh
from vehicle_pose.render.gl import gl_library, thread_context
from vehicle_pose.render.renderer import Renderer, uniform

__all__ = ["FACE_ID_FRAGMENT_SHADER", "FACE_ID_VERTEX_SHADER", "exterior_faces", "sphere_directions"]

log = logging.getLogger(__name__)

# Face ids for the visibility pass of :func:`exterior_faces`, negative where the face is
# seen from behind. The faces are drawn as a triangle soup (three vertices of their own each)
# carrying their id, passed on flat. This gives the same pixels as reading ``gl_PrimitiveID`` in
# the fragment shader from an indexed draw, and Mesa's llvmpipe draws it 1.3-1.5x faster (it
# takes a slower path to hand fragments the primitive id).
FACE_ID_VERTEX_SHADER = """
#version 330
uniform mat4 mvp;
in vec3 in_pos;
flat out int face_id;
void main() {
    gl_Position = mvp * vec4(in_pos, 1.0);
    face_id = gl_VertexID / 3 + 1;
}
"""

FACE_ID_FRAGMENT_SHADER = """
#version 330
flat in int face_id;
layout(location = 0) out float out_id;
void main() {
    float id = float(face_id);
    out_id = gl_FrontFacing ? id : -id;
}
"""


# How far (pixels) a triangle's box must miss every pixel centre to be left out of a view of
# the exterior pass: far more than the gap between this float64 projection and the
# rasteriser's float32 one snapped to its sub-pixel grid (1/256 pixel in llvmpipe).
_SAMPLE_MARGIN = 0.05


def _sampled_faces(points: npt.NDArray[np.float32], faces: npt.NDArray[np.int64], mvp: npt.NDArray[np.float64],
                   size: int, index: npt.NDArray[np.int32]) -> int:
    """Write into ``index`` the corners, in a triangle soup of ``faces`` (face ``f``'s at
    ``3 f .. 3 f + 2``), of the faces that may cover a pixel centre of a ``size`` x ``size``
    view through ``mvp``, in their order; return how many faces.

    A face whose corners' box holds no pixel centre, with :data:`_SAMPLE_MARGIN` to spare,
    gives no fragment, so leaving it out changes no pixel: a software rasteriser pays for each
    triangle it sets up, and most faces of a dense mesh are such slivers (about 60 % of a 500k
    face level in a 512 pixel view). Faces with a corner at or behind the eye are kept.
    """
    n = len(points)
    sx = np.empty(n)
    sy = np.empty(n)
    ok = np.empty(n, np.bool_)
    half = 0.5 * size
    for i in range(n):
        x, y, z = np.float64(points[i, 0]), np.float64(points[i, 1]), np.float64(points[i, 2])
        cx = mvp[0, 0] * x + mvp[0, 1] * y + mvp[0, 2] * z + mvp[0, 3]
        cy = mvp[1, 0] * x + mvp[1, 1] * y + mvp[1, 2] * z + mvp[1, 3]
        cw = mvp[3, 0] * x + mvp[3, 1] * y + mvp[3, 2] * z + mvp[3, 3]
        ok[i] = cw > 1e-6
        if ok[i]:
            sx[i] = (cx / cw + 1.0) * half - 0.5  # pixel centres at whole numbers
            sy[i] = (cy / cw + 1.0) * half - 0.5
    m = _SAMPLE_MARGIN
    count = 0
    for f in range(len(faces)):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        keep = not (ok[a] and ok[b] and ok[c])
        if not keep:
            x0, x1 = min(sx[a], sx[b], sx[c]) - m, max(sx[a], sx[b], sx[c]) + m
            y0, y1 = min(sy[a], sy[b], sy[c]) - m, max(sy[a], sy[b], sy[c]) + m
            keep = np.floor(x1) >= np.ceil(x0) and np.floor(y1) >= np.ceil(y0)
        if keep:
            index[3 * count] = 3 * f
            index[3 * count + 1] = 3 * f + 1
            index[3 * count + 2] = 3 * f + 2
            count += 1
    return count


@functools.cache
def _compiled_sampled_faces() -> Callable[..., int]:
    """:func:`_sampled_faces` compiled by numba (imported on the first exterior pass)."""
    from numba import njit

    return njit(cache=True, nogil=True)(_sampled_faces)


def _software(renderer: Renderer) -> bool:
    """Whether the renderer's OpenGL is Mesa's CPU rasteriser (on a GPU the exterior pass draws
    every face in one lane: choosing faces would cost more than drawing them)."""
    name = str(renderer.ctx.info.get("GL_RENDERER", "")).lower()
    return "llvmpipe" in name or "softpipe" in name


class _GL:
    """The few OpenGL calls the exterior pass makes through ctypes, which lets go of Python's
    lock while they run (moderngl holds it): llvmpipe sets up each context's triangles on the
    calling thread, so contexts drawing in threads share the cores."""

    def __init__(self, lib: ctypes.CDLL) -> None:
        self.use_program = lib.glUseProgram
        self.use_program.argtypes, self.use_program.restype = [ctypes.c_uint], None
        self.bind_vertex_array = lib.glBindVertexArray
        self.bind_vertex_array.argtypes, self.bind_vertex_array.restype = [ctypes.c_uint], None
        self.draw_elements = lib.glDrawElements
        self.draw_elements.argtypes = [ctypes.c_uint, ctypes.c_int, ctypes.c_uint, ctypes.c_void_p]
        self.draw_elements.restype = None
        self.read_pixels = lib.glReadPixels
        self.read_pixels.argtypes = [ctypes.c_int] * 4 + [ctypes.c_uint] * 2 + [ctypes.c_void_p]
        self.read_pixels.restype = None


@functools.cache
def _gl_functions() -> _GL | None:
    """The calls of :class:`_GL` from the GL dispatch library (libglvnd), or None where there is
    none to load (the pass then draws in one lane through moderngl)."""
    lib = gl_library()
    try:
        return None if lib is None else _GL(lib)
    except AttributeError:  # a library without these entry points
        return None


def _lanes() -> int:
    """Contexts drawing the exterior pass's views at once: one per core, up to :data:`_MAX_LANES`."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    return max(1, min(cores, _MAX_LANES))


_MAX_LANES = 4


_HELPERS: dict[int, ThreadPoolExecutor] = {}
_HELPERS_LOCK = threading.Lock()
_LANE = threading.local()


def _helper_pool() -> ThreadPoolExecutor:
    """The process's threads for the further lanes (made again after a fork)."""
    with _HELPERS_LOCK:
        pool = _HELPERS.get(os.getpid())
        if pool is None:
            pool = _HELPERS[os.getpid()] = ThreadPoolExecutor(_MAX_LANES - 1, thread_name_prefix="exterior-lane")
        return pool


def _helper_lane(views: list[npt.NDArray[np.float64]], work: tuple[object, ...]) -> tuple[_F64, _F64]:
    """:func:`_count_views` on a helper thread, with that thread's own context and renderer."""
    renderer = getattr(_LANE, "renderer", None)
    if renderer is None:
        renderer = _LANE.renderer = Renderer(thread_context())
    front, back = _count_views(renderer, views, *work)  # type: ignore[arg-type]
    _check_gl(renderer)
    return front, back


def _check_gl(renderer: Renderer) -> None:
    """Raise :class:`RenderError` where the renderer's context recorded an OpenGL error."""
    err = renderer.ctx.error
    if err != "GL_NO_ERROR":
        raise RenderError(f"OpenGL error while finding the exterior faces: {err}")


def _count_views(renderer: Renderer, views: list[npt.NDArray[np.float64]], points: npt.NDArray[np.float32],
                 faces: npt.NDArray[np.int64], soup: npt.NDArray[np.float32], size: int, software: bool,
                 gl: _GL | None) -> tuple[_F64, _F64]:
    """Pixels each face (1-based; 0: none) won from the front and from behind over ``views``.

    The faces are drawn as a triangle soup indexed by the faces this view may sample
    (:func:`_sampled_faces`, on a software rasteriser; every face elsewhere)."""
    ctx = renderer.ctx
    base = len(faces)
    program = renderer.extra_program("face-ids", FACE_ID_VERTEX_SHADER, FACE_ID_FRAGMENT_SHADER)
    index = np.arange(3 * base, dtype=np.int32)
    select = _compiled_sampled_faces() if software else None
    seen = np.empty(size * size, np.float32)
    front = np.zeros(base + 1)
    back = np.zeros(base + 1)
    resources: list[moderngl.Buffer | moderngl.VertexArray] = []
    try:
        vbo = ctx.buffer(soup.tobytes())
        ibo = ctx.buffer(index.tobytes() if select is None else None, reserve=0 if select is None else index.nbytes)
        vao = ctx.vertex_array(program, [(vbo, "3f", "in_pos")], index_buffer=ibo, index_element_size=4)
        resources += [vao, vbo, ibo]
        ctx.scissor = None
        ctx.enable(moderngl.DEPTH_TEST)
        ctx.disable(moderngl.CULL_FACE | moderngl.BLEND)
        fbo = renderer.framebuffer(size, size, "f4", attributes=False)  # face ids and depth
        fbo.use()
        fbo.viewport = (0, 0, size, size)
        for mvp in views:
            n = base if select is None else select(points, faces, mvp, size, index)
            fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
            if n:
                if select is not None:
                    ibo.write(index[: 3 * n].data)
                uniform(program, "mvp").write(mvp.T.astype("f4").tobytes())
                if gl is None:
                    vao.render(moderngl.TRIANGLES, vertices=3 * n)
                else:
                    gl.use_program(program.glo)
                    gl.bind_vertex_array(vao.glo)
                    gl.draw_elements(_GL_TRIANGLES, 3 * n, _GL_UNSIGNED_INT, None)
            if gl is None:
                fbo.read_into(seen, components=1, attachment=0, dtype="f4")
            else:
                gl.read_pixels(0, 0, size, size, _GL_RED, _GL_FLOAT, seen.ctypes.data)
            ids = seen.astype(np.int64)
            front += np.bincount(ids[ids > 0], minlength=base + 1)
            back += np.bincount(-ids[ids < 0], minlength=base + 1)
    finally:
        for r in resources:
            r.release()
    return front, back


_GL_TRIANGLES, _GL_UNSIGNED_INT, _GL_RED, _GL_FLOAT = 0x0004, 0x1405, 0x1903, 0x1406
_F64 = npt.NDArray[np.float64]


def sphere_directions(count: int) -> npt.NDArray[np.float64]:
    """``count`` unit vectors (count, 3) spread evenly over the sphere (a Fibonacci lattice)."""
    i = np.arange(count) + 0.5
    polar = np.arccos(1.0 - 2.0 * i / count)
    azimuth = np.pi * (1.0 + np.sqrt(5.0)) * i
    return np.stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], axis=1)


def _look_at(direction: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Rotation (3, 3) of a camera looking along ``-direction`` (rows: its x, y, z axes)."""
    z = -direction / np.linalg.norm(direction)
    up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])


def _view_matrices(mesh: Mesh, directions: npt.NDArray[np.float64], distance: float) -> list[npt.NDArray[np.float64]]:
    """Clip transforms (4, 4) of orthographic views along each direction and of perspective
    views from ``distance`` radii away, each framing the mesh's enclosing sphere."""
    centre, radius = mesh.sphere
    radius = max(radius, 1e-9)
    D = distance * radius
    near, far = max(D - 1.01 * radius, 1e-3 * radius), D + 1.01 * radius
    g = np.sqrt(D * D - radius * radius) / radius
    perspective = np.array([[g, 0, 0, 0], [0, g, 0, 0],
                            [0, 0, (far + near) / (far - near), -2 * far * near / (far - near)], [0, 0, 1, 0]])
    orthographic = np.array([[1 / radius, 0, 0, 0], [0, 1 / radius, 0, 0],
                             [0, 0, 1 / (1.01 * radius), -D / (1.01 * radius)], [0, 0, 0, 1]])
    out = []
    for d in directions:
        R = _look_at(d)
        mv = np.eye(4)
        mv[:3, :3] = R
        mv[:3, 3] = -R @ (centre + D * d)
        out += [orthographic @ mv, perspective @ mv]
    return out


# A side of a face counts as seen from outside when it won this share of the face's pixels over
# all views of the exterior pass, or this many pixels (:func:`exterior_faces`).
_SEEN_FRACTION = 0.01
_SEEN_PIXELS = 32.0

_EXTERIOR: weakref.WeakKeyDictionary[Mesh, dict[tuple[int, int, float, float], Mesh]] = weakref.WeakKeyDictionary()
_EXTERIOR_LOCK = threading.Lock()


def exterior_faces(renderer: Renderer, mesh: Mesh, *, directions: int = 64, size: int = 512,
                   distance: float = 2.0, min_hidden: float = 0.05) -> Mesh:
    """The mesh as seen from outside: hidden faces dropped, the others oriented for culling.

    The mesh is drawn with face ids from ``directions`` directions spread over the sphere,
    orthographically and in perspective from ``distance`` times its enclosing radius, each
    framing the whole mesh in ``size`` x ``size`` pixels, noting for every face whether it
    won a pixel's depth test from the front, from behind, or never.

    - Faces never seen are dropped when they are at least ``min_hidden`` of the mesh (the
      cabins and engines of CAD cars); fewer are kept, drawn from both sides.
    - Faces seen from one side only (allowing for ties along outlines, see the code) are
      wound so that side is in front and go into
      :attr:`~vehicle_pose.model.mesh.Part.one_sided` parts, which :meth:`Renderer.render` culls from
      behind: on a closed surface the far half of the faces then costs the rasteriser
      nothing. The winding of Internet CAD does not matter, as it is what was seen that
      decides. Faces seen from both sides (thin sheets, a mirror, a fin) stay two-sided.

    On Mesa's CPU rasteriser each view draws only the faces a pixel centre may fall in
    (:func:`_sampled_faces`), and the views are shared among one context per core (up to
    :data:`_MAX_LANES`) drawing at once, each on its own thread; the pixel counts, and so the
    result, are those of one context drawing every face (tests/render/test_exterior.py).

    Rendering the result gives the same pixels as rendering the mesh (tests/render/test_exterior.py).
    Cached per mesh object and arguments, for every renderer of the process; the pass costs
    0.2-0.5 s for the photoreal models' levels of detail on two CPU cores.
    """
    key = (directions, size, distance, min_hidden)
    with _EXTERIOR_LOCK:
        done = _EXTERIOR.get(mesh, {}).get(key)
    if done is not None:
        return done
    offsets = np.cumsum([0] + [len(p.vertices) for p in mesh.parts])
    points = np.ascontiguousarray(np.concatenate([p.vertices for p in mesh.parts]).astype(np.float32))
    faces = np.ascontiguousarray(np.concatenate(
        [p.faces.astype(np.int64) + o for p, o in zip(mesh.parts, offsets[:-1], strict=True)]))
    base = len(faces)
    soup = np.ascontiguousarray(points[faces])
    views = _view_matrices(mesh, sphere_directions(directions), distance)
    software = _software(renderer)
    gl = _gl_functions() if software else None
    lanes = _lanes() if gl is not None else 1
    work = (points, faces, soup, size, software, gl)
    helpers = [(views[k::lanes], _helper_pool().submit(_helper_lane, views[k::lanes], work)) for k in range(1, lanes)]
    front, back = _count_views(renderer, views[::lanes], *work)
    for share, helper in helpers:
        try:
            more_front, more_back = helper.result()
        except RenderError as exc:  # no second context here: this one draws those views too
            log.warning("exterior pass: a further OpenGL context failed (%s); drawing its views here", exc)
            more_front, more_back = _count_views(renderer, share, *work)
        front += more_front
        back += more_back
    _check_gl(renderer)
    front, back = front[1:], back[1:]
    seen = front + back > 0
    keep_unseen = seen.sum() >= (1.0 - min_hidden) * base
    # Where the near and far faces of a closed surface meet along an outline they tie in
    # depth, and the one drawn first keeps the pixel: a face's far side wins a pixel or two
    # there, under 0.5 % of its pixels on the test shapes and the shipped models. A side is
    # taken as seen from outside when it won at least 1 % of the face's pixels, or 32.
    least = np.minimum(_SEEN_FRACTION * (front + back), _SEEN_PIXELS)
    front_seen, back_seen = seen & (front >= least), seen & (back >= least)
    parts, first = [], 0
    for part in mesh.parts:
        f, b = front_seen[first : first + len(part.faces)], back_seen[first : first + len(part.faces)]
        first += len(part.faces)
        one = f != b
        oriented = np.where((b & ~f)[:, None], part.faces[:, [0, 2, 1]], part.faces)[one]
        two = (f & b) | (~(f | b) & keep_unseen)
        if one.any():
            parts.append(replace(part, faces=np.ascontiguousarray(oriented), one_sided=True))
        if two.any():
            parts.append(part if two.all() else replace(part, faces=part.faces[two], one_sided=False))
    same = len(parts) == len(mesh.parts) and all(a is b for a, b in zip(parts, mesh.parts, strict=True))
    unchanged = not parts or same
    out = mesh if unchanged else Mesh(tuple(parts), source=f"{mesh.source} (exterior)")
    with _EXTERIOR_LOCK:
        _EXTERIOR.setdefault(mesh, {})[key] = out
    return out

