"""Off-screen rendering of per-pixel model attributes (method.md §2).

For a camera (K, R, t) the renderer draws, per pixel, ``(k_a, k_d * phi)`` as float32, where phi
is the interpolated unit surface normal in camera coordinates turned towards the camera, and the
material label of the visible part (0 where the model does not cover the pixel). Only the window
that the model's bounding box projects to is read back, so the cost of a frame follows the
model's size on screen rather than the photo's.

Faces that no view from outside can see are dropped before a mesh is rendered, by the exterior
pass (:mod:`vehicle_pose.render.exterior`), which also orients the faces seen from one side
only so that :meth:`Renderer.render` can cull them from behind.
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import moderngl
import numpy as np
import numpy.typing as npt

from vehicle_pose.clock import current
from vehicle_pose.errors import RenderError
from vehicle_pose.geometry.camera import Camera
from vehicle_pose.model.mesh import KINDS, Mesh
from vehicle_pose.render.buffers import GpuMesh
from vehicle_pose.render.gl import get_context

__all__ = ["Frame", "Renderer", "projection_matrix", "clip_planes", "headlight", "uniform"]

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


def uniform(program: moderngl.Program, name: str) -> moderngl.Uniform:
    """The uniform ``name`` of ``program`` (moderngl's lookup also returns attributes and blocks)."""
    member = program[name]
    if not isinstance(member, moderngl.Uniform):
        raise RenderError(f"the shader has no uniform {name!r}")
    return member


def headlight(attrs: npt.NDArray[np.floating]) -> npt.NDArray[np.floating]:
    """Gray shading ``0.3 k_a + 0.7 k_d |n_z|`` of rendered attributes (..., 4): a light at the camera."""
    shade: npt.NDArray[np.floating] = 0.3 * attrs[..., 0] + 0.7 * np.abs(attrs[..., 3])
    return shade


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


@dataclass(eq=False)
class Frame:
    """Rendered attributes in a window of the image.

    Attributes
    ----------
    attrs : (h, w, 4) float32
        ``(k_a, k_d * nx, k_d * ny, k_d * nz)`` with the normal in camera coordinates;
        undefined where the label is 0 (use :meth:`covered` or the coverage).
    labels : (h, w) uint8
        Material kind + 1 of the visible part (see :data:`vehicle_pose.model.mesh.KINDS`), 0 = empty.
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

    def covered(self, arr: npt.NDArray[Any]) -> npt.NDArray[Any]:
        """Values of a window-shaped array (h, w, ...) at the covered pixels, shape (N, ...)."""
        h, w = self.labels.shape
        return np.take(arr.reshape((h * w,) + arr.shape[2:]), self._window_indices, axis=0)

    def covered_flat_indices(self) -> npt.NDArray[np.intp]:
        """Row-major indices (N,) of the covered pixels in the whole image."""
        r, c = np.divmod(self._window_indices, self.labels.shape[1])
        flat: npt.NDArray[np.intp] = (r + self.y0) * self.width + (c + self.x0)
        return flat

    def full(self, arr: npt.NDArray[Any], fill: float = 0) -> npt.NDArray[Any]:
        """A window-shaped array pasted into a whole-image array (H, W, ...)."""
        out = np.full((self.height, self.width) + arr.shape[2:], fill, dtype=arr.dtype)
        h, w = arr.shape[:2]
        out[self.y0 : self.y0 + h, self.x0 : self.x0 + w] = arr
        return out

    @property
    def coverage(self) -> npt.NDArray[np.bool_]:
        """(H, W) bool: pixels the model covers."""
        return self.full(self.labels > 0)


def _release_framebuffer(fbo: moderngl.Framebuffer) -> None:
    """Free a framebuffer and its renderbuffers (releasing the framebuffer alone keeps them)."""
    attachments = [*fbo.color_attachments, fbo.depth_attachment]
    fbo.release()
    for attachment in attachments:
        if attachment is not None:
            attachment.release()


class Renderer:
    """Renders model attributes for any camera; owns GPU buffers for recently used meshes.

    Parameters
    ----------
    ctx : moderngl.Context, optional
        Defaults to the process's headless context (:func:`vehicle_pose.render.gl.get_context`).
    cache_size : int, keyword-only
        How many meshes keep their GPU buffers.

    While a :mod:`vehicle_pose.clock` runs, :meth:`render` charges its drawing (the context
    finished) to ``draw`` and its read-back to ``read``.
    """

    def __init__(self, ctx: moderngl.Context | None = None, *, cache_size: int = 8) -> None:
        self.ctx = ctx if ctx is not None else get_context()
        self.program = self.ctx.program(vertex_shader=_VERTEX_SHADER, fragment_shader=_FRAGMENT_SHADER)
        uniform(self.program, "tex").value = 0
        self._meshes: OrderedDict[int, GpuMesh] = OrderedDict()
        self._fbos: OrderedDict[tuple[int, int, str, bool], moderngl.Framebuffer] = OrderedDict()
        self._cache_size = cache_size
        self._programs: dict[str, moderngl.Program] = {}

    def _gpu_mesh(self, mesh: Mesh) -> GpuMesh:
        gpu = self._meshes.get(mesh.key)
        if gpu is None:
            gpu = GpuMesh(self.ctx, self.program, mesh)
            self._meshes[mesh.key] = gpu
            while len(self._meshes) > self._cache_size:
                _, old = self._meshes.popitem(last=False)
                old.release()
        else:
            self._meshes.move_to_end(mesh.key)
        return gpu

    def framebuffer(self, width: int, height: int, label_dtype: str = "f1", *,
                    attributes: bool = True) -> moderngl.Framebuffer:
        """A framebuffer of attributes (RGBA float32), labels (one channel) and depth.

        Labels are 8-bit normalised for rendering (a quarter of the bytes to write, clear and
        read of float32), float32 for the exterior pass's face ids, which needs no attributes
        (``attributes=False``: the labels are attachment 0).
        """
        key = (width, height, label_dtype, attributes)
        fbo = self._fbos.get(key)
        if fbo is None:
            # Keep the framebuffer bound last (the most recent entry): creating a framebuffer
            # rebinds the previous one, which must still exist.
            while len(self._fbos) >= 4:
                _release_framebuffer(self._fbos.pop(next(iter(self._fbos))))
            colour = [self.ctx.renderbuffer((width, height), 4, dtype="f4")] if attributes else []
            fbo = self.ctx.framebuffer(
                color_attachments=[*colour, self.ctx.renderbuffer((width, height), 1, dtype=label_dtype)],
                depth_attachment=self.ctx.depth_renderbuffer((width, height)),
            )
            self._fbos[key] = fbo
        else:
            self._fbos.move_to_end(key)
        return fbo

    def extra_program(self, name: str, vertex_shader: str, fragment_shader: str) -> moderngl.Program:
        """A further shader program on this renderer's context, compiled once per ``name`` and
        released with the renderer (the exterior pass draws face ids with one)."""
        program = self._programs.get(name)
        if program is None:
            program = self._programs[name] = self.ctx.program(vertex_shader=vertex_shader,
                                                              fragment_shader=fragment_shader)
        return program

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
        uniform(self.program, "mvp").write(mvp.T.astype("f4").tobytes())
        uniform(self.program, "mv").write(mv.T.astype("f4").tobytes())
        fbo = self.framebuffer(camera.width, camera.height)
        fbo.use()
        fbo.viewport = (0, 0, camera.width, camera.height)
        x0, y0, w, h = win
        self.ctx.scissor = (x0, y0, w, h)
        # Only labels and depth are cleared: the attributes count only where a label is set,
        # and clearing their 16 bytes a pixel cost llvmpipe 10-15 % of a 640x480 frame.
        fbo.color_mask = ((False, False, False, False), (True, True, True, True))  # type: ignore[assignment]
        fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        fbo.color_mask = ((True, True, True, True), (True, True, True, True))  # type: ignore[assignment]
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.disable(moderngl.BLEND)
        self.ctx.front_face = "ccw"
        self.ctx.cull_face = "back"
        clock = current()
        t0 = time.perf_counter() if clock is not None else 0.0
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
            if clock is not None:
                self.ctx.finish()
                t1 = time.perf_counter()
            attrs = np.frombuffer(fbo.read(viewport=win, components=4, attachment=0, dtype="f4"), np.float32)
            labels = np.frombuffer(fbo.read(viewport=win, components=1, attachment=1, dtype="f1"), np.uint8)
            if clock is not None:
                clock.add("draw", t1 - t0)
                clock.add("read", time.perf_counter() - t1)
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

    def release(self) -> None:
        """Free every GPU buffer this renderer holds."""
        for gpu in self._meshes.values():
            gpu.release()
        self._meshes.clear()
        for fbo in self._fbos.values():
            _release_framebuffer(fbo)
        self._fbos.clear()
        self.program.release()
        for program in self._programs.values():
            program.release()
        self._programs.clear()
