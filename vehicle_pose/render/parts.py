"""The part map: which of the car's parts each pixel of the photo shows, at a registered pose.

The model is drawn with face ids (one draw of its full mesh, depth-tested, no culling) in the
photo's own pixels, reduced to at most ``max_size`` on the longer side for very large photos;
each face's part label (:mod:`vehicle_pose.model.parts`) turns the ids into a label image.
Per visible part the map gives its area in the photo's pixels, the share of the part's surface
that is seen and inside the frame, the mean angle between its surface normal and the line of
sight (0 degrees: faced squarely; 90: grazing), and its outline as polygons in photo pixels.
"""

from __future__ import annotations

import io
import json
import weakref
from dataclasses import dataclass
from typing import Any

import cv2
import moderngl
import numpy as np
import numpy.typing as npt

from vehicle_pose.errors import RenderError
from vehicle_pose.geometry.camera import Camera
from vehicle_pose.model.library import VehicleModel
from vehicle_pose.model.mesh import Mesh
from vehicle_pose.model.parts import COLOURS, LEGEND, VOCABULARY, face_geometry
from vehicle_pose.render.exterior import FACE_ID_FRAGMENT_SHADER, FACE_ID_VERTEX_SHADER
from vehicle_pose.render.renderer import Renderer, clip_planes, projection_matrix, uniform

__all__ = ["PartMap", "PartView", "part_map", "palette"]

MAX_SIZE = 1600
"""The longest side (pixels) the part map is drawn at; larger photos get it enlarged."""


def palette() -> list[int]:
    """The label images' palette (256 RGB triples, flat): index 0 black, a part's label its colour."""
    flat = [0, 0, 0]
    for part in VOCABULARY:
        flat += list(COLOURS[part])
    return flat + [0] * (768 - len(flat))


@dataclass(frozen=True)
class PartView:
    """One part as the photo shows it."""

    part: str
    label: int
    pixels: int
    visible_share: float
    incidence_deg: float
    estimated: bool
    polygons: list[list[list[float]]]

    def to_dict(self) -> dict[str, Any]:
        return {"part": self.part, "label": self.label, "pixels": self.pixels,
                "visible_share": round(self.visible_share, 4), "incidence_deg": round(self.incidence_deg, 2),
                "estimated": self.estimated, "polygons": self.polygons}


@dataclass(frozen=True)
class PartMap:
    """The label image (drawn at ``labels.shape``, for a photo of ``width`` x ``height``) and its
    parts, largest first."""

    labels: npt.NDArray[np.uint8]
    width: int
    height: int
    parts: list[PartView]

    def image(self) -> npt.NDArray[np.uint8]:
        """The label image (height, width) at the photo's own size."""
        if self.labels.shape == (self.height, self.width):
            return self.labels
        return np.asarray(cv2.resize(self.labels, (self.width, self.height), interpolation=cv2.INTER_NEAREST))

    def png(self) -> bytes:
        """The label image as an indexed PNG: each pixel its part's label, the palette the
        parts' colours, the legend (part id to label) as JSON in a ``legend`` text chunk."""
        from PIL import Image, PngImagePlugin

        img = Image.fromarray(self.image(), mode="P")
        img.putpalette(palette())
        info = PngImagePlugin.PngInfo()
        info.add_text("legend", json.dumps(LEGEND))
        buf = io.BytesIO()
        img.save(buf, format="PNG", pnginfo=info, optimize=False)
        return buf.getvalue()

    def to_list(self) -> list[dict[str, Any]]:
        return [p.to_dict() for p in self.parts]


_SOUPS: weakref.WeakKeyDictionary[Mesh, tuple[npt.NDArray[np.float32], npt.NDArray[np.float64],
                                              npt.NDArray[np.float64]]] = weakref.WeakKeyDictionary()


def _soup(mesh: Mesh) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """The mesh's faces as a triangle soup (3F, 3) float32, with each face's unit normal (F, 3)
    and area (F,), in the order of :class:`~vehicle_pose.model.parts.PartLabels`."""
    found = _SOUPS.get(mesh)
    if found is None:
        tris, normals, areas, _ = face_geometry(mesh)
        found = (np.ascontiguousarray(tris.reshape(-1, 3), np.float32), normals, areas)
        _SOUPS[mesh] = found
    return found


def _face_ids(renderer: Renderer, mesh: Mesh, camera: Camera) -> npt.NDArray[np.int64]:
    """The face (1-based; 0: none) each pixel of ``camera``'s image shows."""
    W, H = camera.width, camera.height
    planes = clip_planes(mesh, camera)
    win = renderer.window(mesh, camera) if planes is not None else None
    out = np.zeros((H, W), np.int64)
    if planes is None or win is None:
        return out
    soup = _soup(mesh)[0]
    mv = np.eye(4)
    mv[:3, :3], mv[:3, 3] = camera.R, camera.t
    mvp = projection_matrix(camera, *planes) @ mv
    ctx = renderer.ctx
    program = renderer.extra_program("face-ids", FACE_ID_VERTEX_SHADER, FACE_ID_FRAGMENT_SHADER)
    vbo = ctx.buffer(soup.tobytes())
    vao = ctx.vertex_array(program, [(vbo, "3f", "in_pos")])
    x0, y0, w, h = win
    try:
        uniform(program, "mvp").write(mvp.T.astype("f4").tobytes())
        fbo = renderer.framebuffer(W, H, "f4", attributes=False)
        fbo.use()
        fbo.viewport = (0, 0, W, H)
        ctx.scissor = (x0, y0, w, h)
        fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        ctx.enable(moderngl.DEPTH_TEST)
        ctx.disable(moderngl.CULL_FACE | moderngl.BLEND)
        vao.render(moderngl.TRIANGLES)
        ids = np.frombuffer(fbo.read(viewport=win, components=1, attachment=0, dtype="f4"), np.float32)
    finally:
        ctx.scissor = None
        vao.release()
        vbo.release()
    err = ctx.error
    if err != "GL_NO_ERROR":
        raise RenderError(f"OpenGL error while drawing the part map: {err}")
    # The projection puts the image's first row first in the framebuffer, as for Renderer.render.
    out[y0:y0 + h, x0:x0 + w] = np.abs(ids.reshape(h, w)).astype(np.int64)
    return out


def _polygons(mask: npt.NDArray[np.bool_], sx: float, sy: float) -> list[list[list[float]]]:
    """The outlines of a part's pixels as polygons in photo pixels (pieces of 2 pixels or more)."""
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    out = []
    for c in contours:
        if cv2.contourArea(c) < 2.0:
            continue
        c = cv2.approxPolyDP(c, 0.75, True).reshape(-1, 2).astype(np.float64)
        out.append([[round((x + 0.5) * sx - 0.5, 1), round((y + 0.5) * sy - 0.5, 1)] for x, y in c])
    return out


def part_map(model: VehicleModel, camera: Camera, renderer: Renderer, *, max_size: int = MAX_SIZE) -> PartMap:
    """The part map of ``model`` seen by ``camera`` (a camera of the photo's own size)."""
    W, H = camera.width, camera.height
    s = min(1.0, max_size / max(W, H))
    w, h = max(1, round(W * s)), max(1, round(H * s))
    cam = camera if (w, h) == (W, H) else camera.scaled(w, h)
    labels = model.part_labels()
    ids = _face_ids(renderer, model.mesh, cam)
    _, normals, areas = _soup(model.mesh)
    seen = ids > 0
    face = ids[seen] - 1
    image = np.zeros((h, w), np.uint8)
    image[seen] = labels.labels[face]
    # the angle between each pixel's surface normal and its line of sight
    rows, cols = np.nonzero(seen)
    rays = np.column_stack([cols + 0.5, rows + 0.5, np.ones(len(cols))]) @ np.linalg.inv(cam.K).T
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    cosine = np.abs(np.sum((normals[face] @ cam.R.T) * rays, axis=1))
    incidence = np.degrees(np.arccos(np.clip(cosine, 0.0, 1.0)))
    pixel_label = image[seen]
    count = np.bincount(pixel_label, minlength=len(VOCABULARY) + 1)
    angle = np.bincount(pixel_label, weights=incidence, minlength=len(VOCABULARY) + 1)
    shown = np.zeros(len(areas), bool)
    shown[np.unique(face)] = True
    total = np.bincount(labels.labels, weights=areas, minlength=len(VOCABULARY) + 1)
    visible = np.bincount(labels.labels[shown], weights=areas[shown], minlength=len(VOCABULARY) + 1)
    estimated = np.bincount(labels.labels[labels.estimated], minlength=len(VOCABULARY) + 1) > 0
    scale = (W * H) / float(w * h)
    views = []
    for k in np.flatnonzero(count[1:]) + 1:
        views.append(PartView(
            part=VOCABULARY[k - 1], label=int(k), pixels=int(round(count[k] * scale)),
            visible_share=float(visible[k] / total[k]) if total[k] > 0 else 0.0,
            incidence_deg=float(angle[k] / count[k]), estimated=bool(estimated[k]),
            polygons=_polygons(image == k, W / w, H / h)))
    views.sort(key=lambda v: -v.pixels)
    return PartMap(image, W, H, views)
