"""Start poses for the optimiser (method.md §5, step 1).

A client's start camera is used as given. From a vehicle box alone (or, with no hint, a central
box) a coarse sweep over views picks the start: each view is placed so that the model's
projection fills the box, and scored with the invariant loss against a GrabCut foreground of the
box at low resolution.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np
import numpy.typing as npt

from .camera import Camera, look_at_camera
from .errors import CameraError
from .library import VehicleModel
from .loss import InvariantLoss, make_target
from .metadata import parse_axis
from .render import Renderer

__all__ = ["parse_bbox", "central_box", "camera_for_view", "start_from_box"]

Box = tuple[float, float, float, float]


def parse_bbox(value: str | Sequence[float], width: int, height: int) -> Box:
    """A box ``X0,Y0,X1,Y1`` (pixels) checked against the image; CameraError if unusable."""
    try:
        parts = [float(v) for v in (value.split(",") if isinstance(value, str) else value)]
    except (TypeError, ValueError):
        raise CameraError(f"bbox {value!r} must be four numbers X0,Y0,X1,Y1") from None
    if len(parts) != 4 or not all(np.isfinite(parts)):
        raise CameraError(f"bbox {value!r} must be four finite numbers X0,Y0,X1,Y1")
    x0, y0, x1, y1 = parts
    x0, x1 = max(x0, 0.0), min(x1, width - 1.0)
    y0, y1 = max(y0, 0.0), min(y1, height - 1.0)
    if x1 - x0 < 8 or y1 - y0 < 8:
        raise CameraError(f"bbox {value!r} covers too little of the {width}x{height} photo")
    return x0, y0, x1, y1


def central_box(width: int, height: int) -> Box:
    """The box assumed when no hint is given: the central part of the photo."""
    return 0.1 * width, 0.15 * height, 0.9 * width, 0.9 * height


def camera_for_view(
    model: VehicleModel, azimuth_deg: float, elevation_deg: float, box: Box, width: int, height: int, focal: float
) -> Camera:
    """A camera at the given view whose projection of the model fills ``box``."""
    mesh = model.mesh
    up = parse_axis(model.info.up)
    wheels = model.wheels
    fwd = wheels.front_axle_center - wheels.rear_axle_center
    fwd = fwd - (fwd @ up) * up
    fwd /= np.linalg.norm(fwd)
    centre, radius = mesh.sphere
    pts = mesh.box_corners
    bw, bh = box[2] - box[0], box[3] - box[1]
    bc = np.array([0.5 * (box[0] + box[2]), 0.5 * (box[1] + box[3])])
    distance = focal * 2.0 * radius / max(min(bw, bh), 1.0) + radius

    def at(d: float) -> Camera:
        return look_at_camera(
            centre, fwd, up, azimuth_deg=azimuth_deg, elevation_deg=elevation_deg,
            distance=d, focal=focal, width=width, height=height,
        )

    cam = at(distance)
    for _ in range(3):
        uv = cam.project(pts)
        if not np.all(np.isfinite(uv)):
            distance *= 2.0
        else:
            span = uv.max(0) - uv.min(0)
            distance *= max(span[0] / bw, span[1] / bh)
        cam = at(distance)
        uv = cam.project(pts)
        shift = bc - 0.5 * (uv.min(0) + uv.max(0))
        depth = float(cam.to_camera(centre[None])[0, 2])
        t = cam.t + np.array([shift[0], shift[1], 0.0]) * depth / focal
        cam = Camera(cam.K, cam.R, t, width, height)
    return cam


def start_from_box(
    rgb: npt.NDArray[np.uint8],
    model: VehicleModel,
    box: Box,
    renderer: Renderer,
    *,
    max_faces: int = 20000,
    size: int = 160,
    azimuths: Sequence[float] = tuple(range(0, 360, 30)),
    elevations: Sequence[float] = (8.0, 22.0),
) -> Camera:
    """The best of a sweep of views fitted to ``box``, at the photo's size, f = 10 W."""
    H, W = rgb.shape[:2]
    s = min(1.0, size / max(W, H))
    w, h = max(8, round(W * s)), max(8, round(H * s))
    small = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
    sbox = tuple(v * s for v in box)
    mask = np.zeros((h, w), np.uint8)
    rect = (int(sbox[0]), int(sbox[1]), max(2, int(sbox[2] - sbox[0])), max(2, int(sbox[3] - sbox[1])))
    bgd, fgd = np.zeros((1, 65)), np.zeros((1, 65))
    cv2.setRNGSeed(0)
    cv2.grabCut(cv2.cvtColor(small, cv2.COLOR_RGB2BGR), mask, rect, bgd, fgd, 3, cv2.GC_INIT_WITH_RECT)
    fg = (mask == cv2.GC_FGD) | (mask == cv2.GC_PR_FGD)
    loss = InvariantLoss(make_target(small, fg, color=True))
    mesh = model.lod(max_faces)
    best: tuple[float, float, float] | None = None
    for az in azimuths:
        for el in elevations:
            cam = camera_for_view(model, az, el, sbox, w, h, 10.0 * w)
            value = loss(renderer.render(mesh, cam))
            if best is None or value < best[0]:
                best = (value, az, el)
    assert best is not None
    return camera_for_view(model, best[1], best[2], box, W, H, 10.0 * W)
