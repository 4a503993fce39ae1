"""Off-screen rendering of per-pixel model attributes (method.md §2).

For a camera (K, R, t) the renderer draws, per pixel, ``(k_a, k_d * phi)`` as float32, where phi
is the interpolated unit surface normal in camera coordinates turned towards the camera, and the
material label of the visible part (0 where the model does not cover the pixel). Only the window
that the model's bounding box projects to is read back, so the cost of a frame follows the
model's size on screen rather than the photo's.

Faces that no view from outside can see (the cabin, engine and inner shells that CAD models of
cars often carry) are dropped before a mesh is uploaded (:meth:`Renderer.exterior`): they never reach a
pixel, yet each costs as much as a visible face in the rasteriser's set-up. The same pass orients
the faces seen from one side only, so that the renderer can cull them from behind.
"""

from __future__ import annotations

import math
import threading
import weakref
from collections import OrderedDict
from dataclasses import dataclass, replace
from functools import cached_property

import cv2
import moderngl
import numpy as np
import numpy.typing as npt

from .camera import Camera
from .errors import RenderError
from .gl import get_context
from .mesh import KINDS, Mesh

__all__ = ["Frame", "Renderer", "projection_matrix", "clip_planes", "headlight", "sphere_directions"]

_VERTEX_SHADER = """
#version 330
uniform mat4 mvp;
uniform mat4 mv;
in vec3 in_pos;
in vec3 in_normal;
in vec2 in_uv;
in float in_albedo;
in float in_label;
in float in_layer;
out vec3 v_pos;
out vec3 v_normal;
out vec2 v_uv;
out float v_albedo;
flat out float v_label;
flat out float v_layer;
void main() {
    v_label = in_label;
    v_layer = in_layer;
    v_pos = (mv * vec4(in_pos, 1.0)).xyz;
    v_normal = mat3(mv) * in_normal;
    v_uv = in_uv;
    v_albedo = in_albedo;
    gl_Position = mvp * vec4(in_pos, 1.0);
}
"""

# The geometric normal from screen-space derivatives is turned towards the camera, and the
# shading normal is made to agree with it: face winding, which Internet CAD often gets wrong,
# then does not matter.
_FRAGMENT_SHADER = """
#version 330
uniform sampler2DArray tex;
in vec3 v_pos;
in vec3 v_normal;
in vec2 v_uv;
in float v_albedo;
flat in float v_label;
flat in float v_layer;
layout(location = 0) out vec4 out_attr;
layout(location = 1) out float out_label;
void main() {
    // Degenerate (zero-area or zero-normal) geometry must not produce NaN: fall back to the
    // geometric normal, then to facing the camera.
    vec3 ng = cross(dFdx(v_pos), dFdy(v_pos));
    float lg = length(ng);
    ng = lg > 1e-20 ? ng / lg : vec3(0.0, 0.0, -1.0);
    if (dot(ng, v_pos) > 0.0) ng = -ng;
    float len = length(v_normal);
    vec3 n = len > 1e-12 ? v_normal / len : ng;
    if (dot(n, ng) < 0.0) n = -n;
    float k = v_albedo;
    if (v_layer >= 0.0) k *= dot(texture(tex, vec3(v_uv, v_layer)).rgb, vec3(0.299, 0.587, 0.114));
    out_attr = vec4(k, k * n);
    out_label = v_label / 255.0;  // an 8-bit normalised attachment stores the integer
}
"""


# Face ids for the visibility pass of :meth:`Renderer.exterior`, negative where the face is
# seen from behind.
_ID_VERTEX_SHADER = """
#version 330
uniform mat4 mvp;
in vec3 in_pos;
void main() {
    gl_Position = mvp * vec4(in_pos, 1.0);
}
"""

_ID_FRAGMENT_SHADER = """
#version 330
uniform int base;
layout(location = 0) out vec4 out_attr;
layout(location = 1) out float out_id;
void main() {
    out_attr = vec4(0.0);
    float id = float(base + gl_PrimitiveID + 1);
    out_id = gl_FrontFacing ? id : -id;
}
"""


def headlight(attrs: npt.NDArray[np.floating]) -> npt.NDArray[np.floating]:
    """Gray shading ``0.3 k_a + 0.7 k_d |n_z|`` of rendered attributes (..., 4): a light at the camera."""
    return 0.3 * attrs[..., 0] + 0.7 * np.abs(attrs[..., 3])


def clip_planes(mesh: Mesh, camera: Camera) -> tuple[float, float] | None:
    """Near and far depths enclosing the mesh, or None if it lies wholly behind the camera."""
    centre, radius = mesh.sphere
    z = float(camera.to_camera(centre[None])[0, 2])
    far = z + 1.01 * radius
    if far <= 0.0:
        return None
    near = max(z - 1.01 * radius, 1e-4 * radius, far * 1e-5)
    return near, far


def projection_matrix(camera: Camera, near: float, far: float) -> npt.NDArray[np.float64]:
    """OpenGL clip transform (4, 4) for camera-frame points, matching OpenCV pixels exactly.

    Clip y is not flipped: OpenGL framebuffer row r is then image row r (y down), so read-back
    needs no flip. Pixel centres sit at integer pixel coordinates.
    """
    K, W, H = camera.K, camera.width, camera.height
    return np.array(
        [
            [2 * K[0, 0] / W, 2 * K[0, 1] / W, (2 * K[0, 2] + 1) / W - 1, 0.0],
            [0.0, 2 * K[1, 1] / H, (2 * K[1, 2] + 1) / H - 1, 0.0],
            [0.0, 0.0, (far + near) / (far - near), -2 * far * near / (far - near)],
            [0.0, 0.0, 1.0, 0.0],
        ]
    )


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
# all views of the exterior pass, or this many pixels (Renderer.exterior).
_SEEN_FRACTION = 0.01
_SEEN_PIXELS = 32.0

_EXTERIOR: weakref.WeakKeyDictionary[Mesh, dict[tuple[int, int, float, float], Mesh]] = weakref.WeakKeyDictionary()
_EXTERIOR_LOCK = threading.Lock()


@dataclass(eq=False)
class Frame:
    """Rendered attributes in a window of the image.

    Attributes
    ----------
    attrs : (h, w, 4) float32
        ``(k_a, k_d * nx, k_d * ny, k_d * nz)`` with the normal in camera coordinates;
        undefined where the label is 0 (use :meth:`covered` or the coverage).
    labels : (h, w) uint8
        Material kind + 1 of the visible part (see :data:`vehicle_pose.mesh.KINDS`), 0 = empty.
    x0, y0 : int
        Image pixel of the window's top-left element.
    width, height : int
        Size of the whole image.
    """

    attrs: npt.NDArray[np.float32]
    labels: npt.NDArray[np.uint8]
    x0: int
    y0: int
    width: int
    height: int
    n_parts: int = len(KINDS)

    @classmethod
    def empty(cls, width: int, height: int) -> Frame:
        return cls(np.zeros((0, 0, 4), np.float32), np.zeros((0, 0), np.uint8), 0, 0, width, height)

    @cached_property
    def _window_indices(self) -> npt.NDArray[np.intp]:
        return np.flatnonzero(self.labels)

    @property
    def pixel_count(self) -> int:
        """Number of covered pixels."""
        return int(self._window_indices.size)

    def covered(self, arr: npt.NDArray) -> npt.NDArray:
        """Values of a window-shaped array (h, w, ...) at the covered pixels, shape (N, ...)."""
        h, w = self.labels.shape
        return np.take(arr.reshape((h * w,) + arr.shape[2:]), self._window_indices, axis=0)

    def covered_flat_indices(self) -> npt.NDArray[np.intp]:
        """Row-major indices (N,) of the covered pixels in the whole image."""
        r, c = np.divmod(self._window_indices, self.labels.shape[1])
        return (r + self.y0) * self.width + (c + self.x0)

    def full(self, arr: npt.NDArray, fill: float = 0) -> npt.NDArray:
        """A window-shaped array pasted into a whole-image array (H, W, ...)."""
        out = np.full((self.height, self.width) + arr.shape[2:], fill, dtype=arr.dtype)
        h, w = arr.shape[:2]
        out[self.y0 : self.y0 + h, self.x0 : self.x0 + w] = arr
        return out

    @property
    def coverage(self) -> npt.NDArray[np.bool_]:
        """(H, W) bool: pixels the model covers."""
        return self.full(self.labels > 0)


class _GpuMesh:
    """Vertex arrays and textures of one mesh on the GPU: one draw call per sidedness.

    All parts of one sidedness share a draw call: the material label and the texture layer
    (-1 for none) travel as vertex attributes, and the mesh's textures go into one texture
    array, each resized to the largest one's size so that texture coordinates, wrapping and
    mipmaps work per layer as on the texture itself.
    On llvmpipe each draw call has a fixed cost: merging the photoreal models' four or five
    per-texture draws into two made their frames 5-20 % faster at 160-320 pixels. A draw is
    ``(vertex array, cull)``: one-sided parts (:attr:`Part.one_sided`) are culled from behind.
    """

    def __init__(self, ctx: moderngl.Context, program: moderngl.Program, mesh: Mesh) -> None:
        self.draws: list[tuple[moderngl.VertexArray, bool]] = []
        self.texture: moderngl.TextureArray | None = None
        self._resources: list[object] = []
        layers: dict[int, int] = {}
        images: list[npt.NDArray[np.uint8]] = []
        for part in mesh.parts:
            if part.texture is not None and id(part.texture) not in layers:
                layers[id(part.texture)] = len(images)
                images.append(part.texture)
        if images:
            self.texture = ctx.texture_array(*_texture_layers(images))
            self.texture.build_mipmaps()
            self.texture.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
            self.texture.repeat_x = self.texture.repeat_y = True
            self._resources.append(self.texture)
        for one_sided in (True, False):
            parts = [p for p in mesh.parts if p.one_sided == one_sided]
            if not parts:
                continue
            data, faces, offset = [], [], 0
            for part in parts:
                n = len(part.vertices)
                uv = part.uv if part.uv is not None and part.texture is not None else np.zeros((n, 2), np.float32)
                layer = layers[id(part.texture)] if part.texture is not None else -1
                data.append(
                    np.hstack(
                        [
                            part.vertices.astype(np.float32),
                            part.normals.astype(np.float32),
                            uv.astype(np.float32),
                            part.albedo.astype(np.float32)[:, None],
                            np.full((n, 1), part.label, np.float32),
                            np.full((n, 1), layer, np.float32),
                        ]
                    )
                )
                faces.append(part.faces.astype(np.uint32) + offset)
                offset += n
            vbo = ctx.buffer(np.ascontiguousarray(np.vstack(data)).tobytes())
            ibo = ctx.buffer(np.ascontiguousarray(np.vstack(faces)).tobytes())
            vao = ctx.vertex_array(
                program,
                [(vbo, "3f 3f 2f 1f 1f 1f", "in_pos", "in_normal", "in_uv", "in_albedo", "in_label", "in_layer")],
                index_buffer=ibo,
                index_element_size=4,
            )
            self._resources += [vbo, ibo, vao]
            self.draws.append((vao, one_sided))

    def release(self) -> None:
        for r in self._resources:
            r.release()  # type: ignore[attr-defined]
        self._resources.clear()
        self.draws.clear()
        self.texture = None


def _texture_layers(images: list[npt.NDArray[np.uint8]]) -> tuple[tuple[int, int, int], int, bytes]:
    """Size, components and bytes of an RGBA texture array of the images, each resized to the
    largest width and height among them (RGBA: llvmpipe sampled it faster than a one-channel
    luminance array).

    Texture coordinates put v = 0 at the image's bottom row (the OpenGL convention, to which
    trimesh brings every format), and OpenGL's first texel row is v = 0: rows are flipped.
    """
    w = max(img.shape[1] for img in images)
    h = max(img.shape[0] for img in images)
    out = np.full((len(images), h, w, 4), 255, np.uint8)
    for i, img in enumerate(images):
        rgb = np.ascontiguousarray(img[::-1, :, :3])
        if rgb.shape[:2] != (h, w):
            rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_LINEAR)
        out[i, ..., :3] = rgb
    return (w, h, len(images)), 4, out.tobytes()


class Renderer:
    """Renders model attributes for any camera; owns GPU buffers for recently used meshes.

    Parameters
    ----------
    ctx : moderngl.Context, optional
        Defaults to the process's headless context (:func:`vehicle_pose.gl.get_context`).
    cache_size : int, keyword-only
        How many meshes keep their GPU buffers.
    """

    def __init__(self, ctx: moderngl.Context | None = None, *, cache_size: int = 8) -> None:
        self.ctx = ctx if ctx is not None else get_context()
        self.program = self.ctx.program(vertex_shader=_VERTEX_SHADER, fragment_shader=_FRAGMENT_SHADER)
        self.program["tex"].value = 0
        self._meshes: OrderedDict[int, _GpuMesh] = OrderedDict()
        self._fbos: OrderedDict[tuple[int, int, str], moderngl.Framebuffer] = OrderedDict()
        self._cache_size = cache_size
        self._id_program: moderngl.Program | None = None

    def _gpu_mesh(self, mesh: Mesh) -> _GpuMesh:
        gpu = self._meshes.get(mesh.key)
        if gpu is None:
            gpu = _GpuMesh(self.ctx, self.program, mesh)
            self._meshes[mesh.key] = gpu
            while len(self._meshes) > self._cache_size:
                _, old = self._meshes.popitem(last=False)
                old.release()
        else:
            self._meshes.move_to_end(mesh.key)
        return gpu

    def _fbo(self, width: int, height: int, label_dtype: str = "f1") -> moderngl.Framebuffer:
        """A framebuffer of attributes (RGBA float32), labels (one channel) and depth.

        Labels are 8-bit normalised for rendering (a quarter of the bytes to write, clear and
        read of float32), float32 for the exterior pass's face ids.
        """
        key = (width, height, label_dtype)
        fbo = self._fbos.get(key)
        if fbo is None:
            # Keep the framebuffer bound last (the most recent entry): creating a framebuffer
            # rebinds the previous one, which must still exist.
            while len(self._fbos) >= 4:
                self._fbos.pop(next(iter(self._fbos))).release()
            fbo = self.ctx.framebuffer(
                color_attachments=[
                    self.ctx.renderbuffer((width, height), 4, dtype="f4"),
                    self.ctx.renderbuffer((width, height), 1, dtype=label_dtype),
                ],
                depth_attachment=self.ctx.depth_renderbuffer((width, height)),
            )
            self._fbos[key] = fbo
        else:
            self._fbos.move_to_end(key)
        return fbo

    @staticmethod
    def window(mesh: Mesh, camera: Camera) -> tuple[int, int, int, int] | None:
        """Image window (x0, y0, w, h) that holds the model's projection, or None if off-screen."""
        pc = camera.to_camera(mesh.box_corners)
        W, H = camera.width, camera.height
        if np.all(pc[:, 2] > 0):
            uvw = pc @ camera.K.T
            u, v = uvw[:, 0] / uvw[:, 2], uvw[:, 1] / uvw[:, 2]
            x0 = math.floor(u.min()) - 1
            y0 = math.floor(v.min()) - 1
            x1 = math.ceil(u.max()) + 2
            y1 = math.ceil(v.max()) + 2
            x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, W), min(y1, H)
        else:
            x0, y0, x1, y1 = 0, 0, W, H
        if x1 <= x0 or y1 <= y0:
            return None
        return x0, y0, x1 - x0, y1 - y0

    def render(self, mesh: Mesh, camera: Camera) -> Frame:
        """Render ``mesh`` as seen by ``camera``; an empty frame when it is not in view."""
        planes = clip_planes(mesh, camera)
        win = self.window(mesh, camera) if planes is not None else None
        if planes is None or win is None:
            return Frame.empty(camera.width, camera.height)
        near, far = planes
        mv = np.eye(4)
        mv[:3, :3] = camera.R
        mv[:3, 3] = camera.t
        mvp = projection_matrix(camera, near, far) @ mv
        # GLSL matrices are column-major.
        self.program["mvp"].write(mvp.T.astype("f4").tobytes())
        self.program["mv"].write(mv.T.astype("f4").tobytes())
        fbo = self._fbo(camera.width, camera.height)
        fbo.use()
        fbo.viewport = (0, 0, camera.width, camera.height)
        x0, y0, w, h = win
        self.ctx.scissor = (x0, y0, w, h)
        # Only labels and depth are cleared: the attributes count only where a label is set,
        # and clearing their 16 bytes a pixel cost llvmpipe 10-15 % of a 640x480 frame.
        fbo.color_mask = ((False, False, False, False), (True, True, True, True))
        fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        fbo.color_mask = ((True, True, True, True), (True, True, True, True))
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.disable(moderngl.BLEND)
        self.ctx.front_face = "ccw"
        self.ctx.cull_face = "back"
        try:
            gpu = self._gpu_mesh(mesh)
            if gpu.texture is not None:
                gpu.texture.use(0)
            for vao, cull in gpu.draws:
                if cull:
                    self.ctx.enable(moderngl.CULL_FACE)
                else:
                    self.ctx.disable(moderngl.CULL_FACE)
                vao.render(moderngl.TRIANGLES)
            attrs = np.frombuffer(fbo.read(viewport=win, components=4, attachment=0, dtype="f4"), np.float32)
            labels = np.frombuffer(fbo.read(viewport=win, components=1, attachment=1, dtype="f1"), np.uint8)
        finally:
            self.ctx.scissor = None
        err = self.ctx.error
        if err != "GL_NO_ERROR":
            raise RenderError(f"OpenGL error while rendering: {err}")
        return Frame(
            attrs.reshape(h, w, 4),
            labels.reshape(h, w),
            x0,
            y0,
            camera.width,
            camera.height,
        )

    def exterior(self, mesh: Mesh, *, directions: int = 64, size: int = 512, distance: float = 2.0,
                 min_hidden: float = 0.05) -> Mesh:
        """The mesh as seen from outside: hidden faces dropped, the others oriented for culling.

        The mesh is drawn with face ids from ``directions`` directions spread over the sphere,
        orthographically and in perspective from ``distance`` times its enclosing radius, each
        framing the whole mesh in ``size`` x ``size`` pixels, noting for every face whether it
        won a pixel's depth test from the front, from behind, or never.

        - Faces never seen are dropped when they are at least ``min_hidden`` of the mesh (the
          cabins and engines of CAD cars); fewer are kept, drawn from both sides.
        - Faces seen from one side only (allowing for ties along outlines, see the code) are
          wound so that side is in front and go into
          :attr:`~vehicle_pose.mesh.Part.one_sided` parts, which :meth:`render` culls from
          behind: on a closed surface the far half of the faces then costs the rasteriser
          nothing. The winding of Internet CAD does not matter, as it is what was seen that
          decides. Faces seen from both sides (thin sheets, a mirror, a fin) stay two-sided.

        Rendering the result gives the same pixels as rendering the mesh (tests/test_render.py).
        Cached per mesh object and arguments, for every renderer of the process; the pass costs
        0.3-0.7 s for the photoreal models' levels of detail on two CPU cores.
        """
        key = (directions, size, distance, min_hidden)
        with _EXTERIOR_LOCK:
            done = _EXTERIOR.get(mesh, {}).get(key)
        if done is not None:
            return done
        if self._id_program is None:
            self._id_program = self.ctx.program(vertex_shader=_ID_VERTEX_SHADER, fragment_shader=_ID_FRAGMENT_SHADER)
        program = self._id_program
        draws, resources, base = [], [], 0
        try:
            for part in mesh.parts:
                vbo = self.ctx.buffer(np.ascontiguousarray(part.vertices, dtype=np.float32).tobytes())
                ibo = self.ctx.buffer(np.ascontiguousarray(part.faces, dtype=np.uint32).tobytes())
                vao = self.ctx.vertex_array(program, [(vbo, "3f", "in_pos")], index_buffer=ibo, index_element_size=4)
                resources += [vao, ibo, vbo]
                draws.append((vao, base))
                base += len(part.faces)
            front = np.zeros(base + 1)
            back = np.zeros(base + 1)
            self.ctx.scissor = None
            self.ctx.enable(moderngl.DEPTH_TEST)
            self.ctx.disable(moderngl.CULL_FACE | moderngl.BLEND)
            fbo = self._fbo(size, size, "f4")
            fbo.use()
            fbo.viewport = (0, 0, size, size)
            for mvp in _view_matrices(mesh, sphere_directions(directions), distance):
                program["mvp"].write(mvp.T.astype("f4").tobytes())
                fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
                for vao, first in draws:
                    program["base"].value = first
                    vao.render(moderngl.TRIANGLES)
                ids = np.frombuffer(fbo.read(components=1, attachment=1, dtype="f4"), np.float32).astype(np.int64)
                front += np.bincount(ids[ids > 0], minlength=base + 1)
                back += np.bincount(-ids[ids < 0], minlength=base + 1)
        finally:
            for r in resources:
                r.release()  # type: ignore[attr-defined]
        err = self.ctx.error
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
        front, back = seen & (front >= least), seen & (back >= least)
        parts, first = [], 0
        for part in mesh.parts:
            f, b = front[first : first + len(part.faces)], back[first : first + len(part.faces)]
            first += len(part.faces)
            one = f != b
            oriented = np.where((b & ~f)[:, None], part.faces[:, [0, 2, 1]], part.faces)[one]
            two = (f & b) | (~(f | b) & keep_unseen)
            if one.any():
                parts.append(replace(part, faces=np.ascontiguousarray(oriented), one_sided=True))
            if two.any():
                parts.append(part if two.all() else replace(part, faces=part.faces[two], one_sided=False))
        unchanged = not parts or (len(parts) == len(mesh.parts) and all(a is b for a, b in zip(parts, mesh.parts)))
        out = mesh if unchanged else Mesh(tuple(parts), source=f"{mesh.source} (exterior)")
        with _EXTERIOR_LOCK:
            _EXTERIOR.setdefault(mesh, {})[key] = out
        return out

    def release(self) -> None:
        """Free every GPU buffer this renderer holds."""
        for gpu in self._meshes.values():
            gpu.release()
        self._meshes.clear()
        for fbo in self._fbos.values():
            fbo.release()
        self._fbos.clear()
        self.program.release()
        if self._id_program is not None:
            self._id_program.release()
            self._id_program = None
