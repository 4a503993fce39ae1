"""A mesh's vertex arrays and textures on the GPU, as the renderer draws them."""

from __future__ import annotations

import cv2
import moderngl
import numpy as np
import numpy.typing as npt

from vehicle_pose.model.mesh import Mesh

__all__ = ["GpuMesh", "texture_layers"]


class GpuMesh:
    """Vertex arrays and textures of one mesh on the GPU: one draw call per sidedness.

    All parts of one sidedness share a draw call: the material label and the texture layer
    (-1 for none) travel as vertex attributes, and the mesh's textures go into one texture
    array, each resized to the largest one's size so that texture coordinates, wrapping and
    mipmaps work per layer as on the texture itself.
    On llvmpipe each draw call has a fixed cost: merging the photoreal models' four or five
    per-texture draws into two made their frames 5-20 % faster at 160-320 pixels. A draw is
    ``(vertex array, cull)``: one-sided parts (:attr:`Part.one_sided`) are culled from behind.
    The buffers are made once; each program that draws them gets its own vertex arrays
    (:meth:`draws_for`), ``program``'s at once (:attr:`draws`).
    """

    def __init__(self, ctx: moderngl.Context, program: moderngl.Program, mesh: Mesh) -> None:
        self.ctx = ctx
        self.texture: moderngl.TextureArray | None = None
        self._resources: list[object] = []
        self._buffers: list[tuple[moderngl.Buffer, moderngl.Buffer, bool]] = []
        self._draws: dict[int, list[tuple[moderngl.VertexArray, bool]]] = {}
        layers: dict[int, int] = {}
        images: list[npt.NDArray[np.uint8]] = []
        for part in mesh.parts:
            if part.texture is not None and id(part.texture) not in layers:
                layers[id(part.texture)] = len(images)
                images.append(part.texture)
        if images:
            self.texture = ctx.texture_array(*texture_layers(images))
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
            self._resources += [vbo, ibo]
            self._buffers.append((vbo, ibo, one_sided))
        self.draws = self.draws_for(program)

    def draws_for(self, program: moderngl.Program) -> list[tuple[moderngl.VertexArray, bool]]:
        """The draws of this mesh by ``program`` (its vertex arrays made on first use)."""
        draws = self._draws.get(program.glo)
        if draws is None:
            draws = self._draws[program.glo] = []
            for vbo, ibo, one_sided in self._buffers:
                vao = self.ctx.vertex_array(
                    program,
                    [(vbo, "3f 3f 2f 1f 1f 1f", "in_pos", "in_normal", "in_uv", "in_albedo", "in_label", "in_layer")],
                    index_buffer=ibo,
                    index_element_size=4,
                )
                self._resources.append(vao)
                draws.append((vao, one_sided))
        return draws

    def release(self) -> None:
        for r in reversed(self._resources):
            r.release()  # type: ignore[attr-defined]
        self._resources.clear()
        self._draws.clear()
        self.draws.clear()
        self.texture = None


def texture_layers(images: list[npt.NDArray[np.uint8]]) -> tuple[tuple[int, int, int], int, bytes]:
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
