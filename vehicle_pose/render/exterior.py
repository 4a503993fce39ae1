"""The exterior pass: the faces of a mesh that some view from outside sees.

Faces that no view from outside can see (the cabin, engine and inner shells that CAD models of
cars often carry) never reach a pixel, yet each costs as much as a visible face in the
rasteriser's set-up; :func:`exterior_faces` drops them and orients the faces seen from one side
only, so that the renderer can cull them from behind.
"""

from __future__ import annotations

import threading
import weakref
from dataclasses import replace

import moderngl
import numpy as np
import numpy.typing as npt

from vehicle_pose.errors import RenderError
from vehicle_pose.model.mesh import Mesh
from vehicle_pose.render.renderer import Renderer, uniform

__all__ = ["exterior_faces", "sphere_directions"]

# Face ids for the visibility pass of :func:`exterior_faces`, negative where the face is
# seen from behind. The faces are drawn as a triangle soup (three vertices of their own each),
# so a face's id is its first vertex's index over three, passed on flat. This gives the same
# pixels as reading ``gl_PrimitiveID`` in the fragment shader from an indexed draw, and Mesa's
# llvmpipe draws it 1.3-1.5x faster (it takes a slower path to hand fragments the primitive id).
_ID_VERTEX_SHADER = """
#version 330
uniform mat4 mvp;
uniform int base;
in vec3 in_pos;
flat out int face_id;
void main() {
    gl_Position = mvp * vec4(in_pos, 1.0);
    face_id = base + gl_VertexID / 3 + 1;
}
"""

_ID_FRAGMENT_SHADER = """
#version 330
flat in int face_id;
layout(location = 0) out float out_id;
void main() {
    float id = float(face_id);
    out_id = gl_FrontFacing ? id : -id;
}
"""


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

    Rendering the result gives the same pixels as rendering the mesh (tests/render/test_exterior.py).
    Cached per mesh object and arguments, for every renderer of the process; the pass costs
    0.3-0.7 s for the photoreal models' levels of detail on two CPU cores.
    """
    key = (directions, size, distance, min_hidden)
    with _EXTERIOR_LOCK:
        done = _EXTERIOR.get(mesh, {}).get(key)
    if done is not None:
        return done
    program = renderer.extra_program("face-ids", _ID_VERTEX_SHADER, _ID_FRAGMENT_SHADER)
    draws, resources, base = [], [], 0
    try:
        for part in mesh.parts:
            soup = np.ascontiguousarray(part.vertices.astype(np.float32)[part.faces])
            vbo = renderer.ctx.buffer(soup.tobytes())
            vao = renderer.ctx.vertex_array(program, [(vbo, "3f", "in_pos")])
            resources += [vao, vbo]
            draws.append((vao, base))
            base += len(part.faces)
        front = np.zeros(base + 1)
        back = np.zeros(base + 1)
        renderer.ctx.scissor = None
        renderer.ctx.enable(moderngl.DEPTH_TEST)
        renderer.ctx.disable(moderngl.CULL_FACE | moderngl.BLEND)
        fbo = renderer.framebuffer(size, size, "f4", attributes=False)  # face ids and depth
        fbo.use()
        fbo.viewport = (0, 0, size, size)
        for mvp in _view_matrices(mesh, sphere_directions(directions), distance):
            uniform(program, "mvp").write(mvp.T.astype("f4").tobytes())
            fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
            for vao, first in draws:
                uniform(program, "base").value = first
                vao.render(moderngl.TRIANGLES)
            ids = np.frombuffer(fbo.read(components=1, attachment=0, dtype="f4"), np.float32).astype(np.int64)
            front += np.bincount(ids[ids > 0], minlength=base + 1)
            back += np.bincount(-ids[ids < 0], minlength=base + 1)
    finally:
        for r in resources:
            r.release()  # type: ignore[attr-defined]
    err = renderer.ctx.error
    if err != "GL_NO_ERROR":
        raise RenderError(f"OpenGL error while finding the exterior faces: {err}")
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

