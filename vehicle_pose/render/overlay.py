"""Overlay images: the registered model's outline (and optionally its shading) on the photo."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt

from vehicle_pose.geometry.camera import Camera
from vehicle_pose.geometry.pose import visible_side
from vehicle_pose.model.mesh import Mesh
from vehicle_pose.model.metadata import WheelGeometry
from vehicle_pose.model.parts import COLOURS
from vehicle_pose.render.parts import PartMap, palette
from vehicle_pose.render.renderer import Renderer, headlight

__all__ = ["draw_overlay", "encode_image", "save_png"]

_OUTLINE = (255, 220, 0)
_PARTS = (0, 200, 255)
_WHEELS = (255, 60, 60)


def draw_overlay(
    photo: npt.NDArray[np.uint8],
    mesh: Mesh,
    camera: Camera,
    *,
    renderer: Renderer | None = None,
    wheels: WheelGeometry | None = None,
    shade: float = 0.0,
    thickness: int | None = None,
    parts: PartMap | None = None,
    tint: float = 0.45,
) -> npt.NDArray[np.uint8]:
    """The photo (H, W, 3) uint8 RGB with the model's outline drawn at ``camera``.

    The silhouette is drawn in yellow, boundaries between material parts in cyan and the centres
    of the wheels whose outer face looks at the camera in red (the far side's are behind the
    body). ``shade`` in [0, 1] blends a head-light shaded render of the model in.
    With a part map (:mod:`vehicle_pose.render.parts`, for the same camera), each part is tinted
    in its colour (``tint``: how much) and a legend of the parts seen is drawn in the corner
    where it hides the fewest of the model's pixels (top left where none).
    """
    r = renderer if renderer is not None else Renderer()
    H, W = photo.shape[:2]
    cam = camera if (camera.width, camera.height) == (W, H) else camera.scaled(W, H)
    frame = r.render(mesh, cam)
    out = photo.copy()
    t = thickness if thickness is not None else max(1, round(max(W, H) / 500))
    if frame.pixel_count == 0:
        return out
    labels = frame.full(frame.labels)
    if shade > 0.0:
        # Covered pixels come in the same (row-major) order from the window and the image.
        gray = np.clip(headlight(frame.covered(frame.attrs)), 0.0, 1.0) * 255.0
        cov = labels > 0
        out[cov] = ((1.0 - shade) * out[cov] + shade * gray[:, None]).astype(np.uint8)
    if parts is not None:
        _tint_parts(out, parts, tint)
    edges = np.zeros((H, W), np.uint8)
    edges[:, 1:] |= labels[:, 1:] != labels[:, :-1]
    edges[1:, :] |= labels[1:, :] != labels[:-1, :]
    edges &= (labels > 0) | np.roll(labels > 0, 1, axis=0) | np.roll(labels > 0, 1, axis=1)
    if t > 1:
        edges = cv2.dilate(edges, np.ones((t, t), np.uint8))
    out[edges > 0] = _PARTS
    contours, _ = cv2.findContours((labels > 0).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(out, contours, -1, _OUTLINE, t + 1, lineType=cv2.LINE_AA)
    if wheels is not None:
        for x, y in _seen_hubs(wheels, cam):
            cv2.circle(out, (int(round(x)), int(round(y))), 2 * t + 2, _WHEELS, -1, lineType=cv2.LINE_AA)
    if parts is not None:
        _legend(out, parts, labels > 0)
    return out


def _seen_hubs(wheels: WheelGeometry, camera: Camera) -> npt.NDArray[np.float64]:
    """The pixels (N, 2) of the wheel centres of the side whose outward axle points towards the
    camera (:func:`~vehicle_pose.geometry.pose.visible_side`; none behind it)."""
    near = wheels.side(visible_side(camera, wheels.side("left")))
    uv = camera.project(np.stack([near.rear, near.front]))
    seen: npt.NDArray[np.float64] = uv[np.all(np.isfinite(uv), axis=1)]
    return seen


def _tint_parts(out: npt.NDArray[np.uint8], parts: PartMap, tint: float) -> None:
    """Blend each part's colour into the pixels it covers."""
    H, W = out.shape[:2]
    labels = parts.labels
    if labels.shape != (H, W):
        labels = cv2.resize(labels, (W, H), interpolation=cv2.INTER_NEAREST)
    colours = np.array(palette(), np.float32).reshape(256, 3)
    cov = labels > 0
    out[cov] = ((1.0 - tint) * out[cov] + tint * colours[labels[cov]]).astype(np.uint8)


def _legend(out: npt.NDArray[np.uint8], parts: PartMap, covered: npt.NDArray[np.bool_], most: int = 14) -> None:
    """A legend of the largest parts seen (colour and name) on a dark panel, in the corner of
    the picture where the panel hides the fewest ``covered`` pixels (the model's; the first
    of top left, top right, bottom left, bottom right on a tie)."""
    H, W = out.shape[:2]
    shown = parts.parts[:most]
    if not shown:
        return
    scale = max(0.7, min(W, H) / 700)  # legible on a 640-pixel overlay, in proportion above
    line = int(round(22 * scale))
    box = int(round(14 * scale))
    width = min(W, int(round(230 * scale)))
    height = min(H, line * len(shown) + line // 2)
    gap = int(round(8 * scale))
    corners = [(x, y) for y in (gap, H - gap - height) for x in (gap, W - gap - width)]
    corners = [(max(0, x), max(0, y)) for x, y in corners]
    x0, y0 = min(corners, key=lambda c: int(covered[c[1]:c[1] + height, c[0]:c[0] + width].sum()))
    x1, y1 = min(W, x0 + width), min(H, y0 + height)
    out[y0:y1, x0:x1] = (0.35 * out[y0:y1, x0:x1]).astype(np.uint8)
    for k, view in enumerate(shown):
        y = y0 + line // 2 + k * line
        cv2.rectangle(out, (x0 + 6, y), (x0 + 6 + box, y + box), COLOURS[view.part], -1)
        cv2.putText(out, view.part.replace("_", " "), (x0 + 12 + box, y + box - 1), cv2.FONT_HERSHEY_SIMPLEX,
                    0.45 * scale, (255, 255, 255), max(1, round(scale)), cv2.LINE_AA)


def encode_image(rgb: npt.NDArray[np.uint8], ext: str = ".png", params: Sequence[int] = ()) -> bytes:
    """An (H, W, 3) uint8 RGB array encoded in the format of ``ext`` (``".png"``, ``".jpg"``)."""
    ok, buf = cv2.imencode(ext, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), list(params))
    if not ok:
        raise ValueError(f"cannot encode an image as {ext}")
    return buf.tobytes()


def save_png(path: str | Path, rgb: npt.NDArray[np.uint8]) -> None:
    """Write an RGB array as PNG (creating the folder)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_bytes(encode_image(rgb, ".png"))
