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

import logging
import math
import time
from collections import OrderedDict
from collections.abc import Sequence
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
from vehicle_pose.render.layers import MAX_LAYERS, LayeredTarget, supported

__all__ = ["Frame", "Renderer", "projection_matrix", "clip_planes", "headlight", "uniform"]

log = logging.getLogger(__name__)

_LAYER_BUDGET = 128 << 20
"""Memory a size's layered target may take (bytes): 100 layers up to 320 x 190, 19 at 640 x 480."""

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

# The same for many poses in one instanced draw (:mod:`vehicle_pose.render.layers`): instance i
# takes the i-th matrices and draws into layer i; the arithmetic is the single draw's.
_LAYERED_VERTEX_SHADER = _VERTEX_SHADER.replace(
    "#version 330\n",
    "#version 330\n#extension GL_ARB_shader_viewport_layer_array : enable\n"
    "#extension GL_AMD_vertex_shader_layer : enable\n",
).replace(
    "uniform mat4 mvp;\nuniform mat4 mv;\n",
    f"uniform mat4 mvps[{MAX_LAYERS}];\nuniform mat4 mvs[{MAX_LAYERS}];\n",
).replace(
    "void main() {\n",
    "void main() {\n    mat4 mvp = mvps[gl_InstanceID];\n    mat4 mv = mvs[gl_InstanceID];\n"
    "    gl_Layer = gl_InstanceID;\n",
)

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


def _matrices(camera: Camera, near: float, far: float) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """The model-view-projection and model-view matrices of ``camera`` (row-major, float64)."""
    mv = np.eye(4)
    mv[:3, :3] = camera.R
    mv[:3, 3] = camera.t
    return projection_matrix(camera, near, far) @ mv, mv


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


_Pose = tuple[int, Camera, tuple[float, float], tuple[int, int, int, int]]
"""A pose :meth:`Renderer.render_many` draws: its index, camera, clip planes and window."""


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
    layers : bool, keyword-only
        Whether :meth:`render_many` may draw poses together, in layers, where the context can
        (the frames are the same either way).

    While a :mod:`vehicle_pose.clock` runs, :meth:`render` and :meth:`render_many` charge their
    drawing (the context finished) to ``draw`` and their read-back to ``read``, one call a pose.
    """

    def __init__(self, ctx: moderngl.Context | None = None, *, cache_size: int = 8, layers: bool = True) -> None:
        self.ctx = ctx if ctx is not None else get_context()
        self.layers = layers
        self.program = self.ctx.program(vertex_shader=_VERTEX_SHADER, fragment_shader=_FRAGMENT_SHADER)
        uniform(self.program, "tex").value = 0
        self._meshes: OrderedDict[int, GpuMesh] = OrderedDict()
        self._fbos: OrderedDict[tuple[int, int, str, bool], moderngl.Framebuffer] = OrderedDict()
        self._cache_size = cache_size
        self._programs: dict[str, moderngl.Program] = {}
        self._targets: OrderedDict[tuple[int, int], LayeredTarget] = OrderedDict()

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
        mvp, mv = _matrices(camera, *planes)
        # GLSL matrices are column-major.
        uniform(self.program, "mvp").write(mvp.T.astype("f4").tobytes())
        uniform(self.program, "mv").write(mv.T.astype("f4").tobytes())
        fbo = self.framebuffer(camera.width, camera.height)
        x0, y0, w, h = win
        self._begin(fbo, camera.width, camera.height, win)
        clock = current()
        t0 = time.perf_counter() if clock is not None else 0.0
        try:
            gpu = self._gpu_mesh(mesh)
            self._draw(gpu, gpu.draws, 1)
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
        self._check()
        return Frame(
            attrs.reshape(h, w, 4),
            labels.reshape(h, w),
            x0,
            y0,
            camera.width,
            camera.height,
        )

    def render_many(self, mesh: Mesh, cameras: Sequence[Camera]) -> list[Frame]:
        """:meth:`render` of each camera, in order, each frame the same bit for bit. Cameras of
        one image size are drawn up to :data:`~vehicle_pose.render.layers.MAX_LAYERS` at a time,
        each into a layer of a layered target (:mod:`vehicle_pose.render.layers`), where the
        context can and the size's target fits ``_LAYER_BUDGET``; else one at a time."""
        frames: list[Frame | None] = [None] * len(cameras)
        drawn: list[_Pose] = []
        for i, camera in enumerate(cameras):
            planes = clip_planes(mesh, camera)
            win = self.window(mesh, camera) if planes is not None else None
            if planes is None or win is None:
                frames[i] = Frame.empty(camera.width, camera.height)
            else:
                drawn.append((i, camera, planes, win))
        sizes = {(camera.width, camera.height) for _, camera, _, _ in drawn}
        target = self._target(*sizes.pop()) if len(drawn) > 1 and len(sizes) == 1 else None
        if target is None:
            for i, camera, _, _ in drawn:
                frames[i] = self.render(mesh, camera)
        else:
            for first in range(0, len(drawn), target.layers):
                self._render_layers(mesh, drawn[first : first + target.layers], target, frames)
        return [f for f in frames if f is not None]

    def _render_layers(self, mesh: Mesh, drawn: list[_Pose], target: LayeredTarget,
                       frames: list[Frame | None]) -> None:
        """Draw ``drawn`` into the layers of ``target``, each frame to its index in ``frames``."""
        program = self._layered
        assert program is not None
        mvps = np.zeros((MAX_LAYERS, 4, 4), np.float32)
        mvs = np.zeros((MAX_LAYERS, 4, 4), np.float32)
        for k, (_, camera, planes, _) in enumerate(drawn):
            mvp, mv = _matrices(camera, *planes)
            mvps[k], mvs[k] = mvp.T, mv.T
        uniform(program, "mvps").write(mvps.tobytes())
        uniform(program, "mvs").write(mvs.tobytes())
        # One scissor for every layer: the union of the windows (each pose draws only in its own).
        windows = np.array([win for _, _, _, win in drawn])
        x0, y0 = windows[:, :2].min(0)
        x1, y1 = (windows[:, :2] + windows[:, 2:]).max(0)
        scissor = (int(x0), int(y0), int(x1 - x0), int(y1 - y0))
        target.clear(len(drawn), scissor)
        self._begin(target.fbo, target.width, target.height, scissor, clear=False)
        clock = current()
        t0 = time.perf_counter() if clock is not None else 0.0
        try:
            gpu = self._gpu_mesh(mesh)
            self._draw(gpu, gpu.draws_for(program), len(drawn))
            if clock is not None:
                self.ctx.finish()
                t1 = time.perf_counter()
            for layer, (i, camera, _, win) in enumerate(drawn):
                attrs, labels = target.read(layer, win)
                frames[i] = Frame(attrs, labels, win[0], win[1], camera.width, camera.height)
            if clock is not None:
                clock.add("draw", t1 - t0, calls=len(drawn))
                clock.add("read", time.perf_counter() - t1, calls=len(drawn))
        finally:
            self.ctx.scissor = None
        self._check()

    def _begin(self, fbo: moderngl.Framebuffer, width: int, height: int, scissor: tuple[int, int, int, int],
               clear: bool = True) -> None:
        """Bind ``fbo``, clear its labels and depth within ``scissor`` (unless the caller has,
        ``clear=False``) and set the draw's state."""
        fbo.use()
        fbo.viewport = (0, 0, width, height)
        self.ctx.scissor = scissor
        if clear:
            # Only labels and depth are cleared: the attributes count only where a label is set,
            # and clearing their 16 bytes a pixel cost llvmpipe 10-15 % of a 640x480 frame.
            fbo.color_mask = ((False, False, False, False), (True, True, True, True))  # type: ignore[assignment]
            fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
            fbo.color_mask = ((True, True, True, True), (True, True, True, True))  # type: ignore[assignment]
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.disable(moderngl.BLEND)
        self.ctx.front_face = "ccw"
        self.ctx.cull_face = "back"

    def _draw(self, gpu: GpuMesh, draws: list[tuple[moderngl.VertexArray, bool]], instances: int) -> None:
        """Draw ``gpu``'s ``draws`` (its vertex arrays for one program), ``instances`` times."""
        if gpu.texture is not None:
            gpu.texture.use(0)
        for vao, cull in draws:
            if cull:
                self.ctx.enable(moderngl.CULL_FACE)
            else:
                self.ctx.disable(moderngl.CULL_FACE)
            vao.render(moderngl.TRIANGLES, instances=instances)

    def _check(self) -> None:
        err = self.ctx.error
        if err != "GL_NO_ERROR":
            raise RenderError(f"OpenGL error while rendering: {err}")

    @property
    def draws_layers(self) -> bool:
        """Whether :meth:`render_many` draws poses together on this context."""
        return self.layers and self._layered is not None

    @cached_property
    def _layered(self) -> moderngl.Program | None:
        """The program of the layered draws, None where the context cannot draw them (or the
        renderer is not to)."""
        if not self.layers or not supported(self.ctx):
            return None
        try:
            program = self.ctx.program(vertex_shader=_LAYERED_VERTEX_SHADER, fragment_shader=_FRAGMENT_SHADER)
        except moderngl.Error as exc:
            log.info("poses are drawn one at a time: the layered program does not build (%s)", exc)
            return None
        uniform(program, "tex").value = 0
        return program

    def _target(self, width: int, height: int) -> LayeredTarget | None:
        """The layered target of that size (made on first use; the two used last are kept);
        None where the context draws no layers or two layers of that size exceed the budget."""
        target = self._targets.get((width, height))
        if target is not None:
            self._targets.move_to_end((width, height))
            return target
        layers = min(MAX_LAYERS, _LAYER_BUDGET // LayeredTarget.nbytes(width, height, 1))
        if layers < 2 or not self.draws_layers:
            return None
        while len(self._targets) >= 2:
            self._release_target(self._targets.pop(next(iter(self._targets))))
        try:
            target = LayeredTarget(self.ctx, width, height, layers)
        except RenderError as exc:  # a driver that will not make the layered framebuffer
            log.info("poses are drawn one at a time: %s", exc)
            self.layers = False
            return None
        self._targets[(width, height)] = target
        return target

    def _release_target(self, target: LayeredTarget) -> None:
        # moderngl rebinds the framebuffer it bound last whenever it makes one: bind a live one.
        self.framebuffer(target.width, target.height).use()
        target.release()

    def release(self) -> None:
        """Free every GPU buffer this renderer holds, leaving the context's own framebuffer bound
        (moderngl rebinds the framebuffer bound last whenever it makes one: a renderer made
        after this one on the same context must not find a freed one there)."""
        for target in self._targets.values():
            self._release_target(target)
        self._targets.clear()
        self.ctx.detect_framebuffer(0).use()
        # Asking a surfaceless context's framebuffer 0 for its attachments may record an error
        # on some drivers (not on llvmpipe); the binding itself is always valid.
        _ = self.ctx.error
        for gpu in self._meshes.values():
            gpu.release()
        self._meshes.clear()
        for fbo in self._fbos.values():
            _release_framebuffer(fbo)
        self._fbos.clear()
        self.program.release()
        layered = self.__dict__.get("_layered")
        if layered is not None:
            layered.release()
        for program in self._programs.values():
            program.release()
        self._programs.clear()
