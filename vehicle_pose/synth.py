"""Synthetic photos with known ground truth, made by the project's own renderer.

The model is rendered at a known camera and lit by the Lambertian model of the paper,
``colour = ambient * k_a + diffuse * (L . k_d phi) + offset`` per channel, which is linear in
the rendered attributes; a negative lighting flips it. It is composited over a textured random
background with sensor noise. Used by the tests, the benchmark and the shipped sample photo.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from .camera import Camera
from .library import VehicleModel
from .mesh import Mesh
from .render import Renderer

__all__ = ["Lighting", "LIGHTINGS", "synthesize", "random_framed_view"]


@dataclass(frozen=True)
class Lighting:
    """Per-channel ambient and diffuse colours, light direction (camera frame), offset, negation."""

    ambient: tuple[float, float, float]
    diffuse: tuple[float, float, float]
    direction: tuple[float, float, float]
    offset: float = 0.0
    negative: bool = False


LIGHTINGS: dict[str, Lighting] = {
    "front": Lighting((0.25, 0.25, 0.28), (0.5, 0.45, 0.4), (0.2, -0.5, -1.0), 0.35),
    "side": Lighting((0.15, 0.12, 0.1), (0.5, 0.45, 0.4), (-1.0, -0.3, -0.3), 0.35),
    "top": Lighting((0.3, 0.3, 0.3), (0.45, 0.5, 0.55), (0.0, -1.0, -0.2), 0.35),
    "negative": Lighting((0.25, 0.25, 0.25), (0.5, 0.5, 0.5), (0.3, -0.4, -1.0), 0.3, negative=True),
}


def _background(height: int, width: int, rng: np.random.Generator) -> npt.NDArray[np.float64]:
    layers = np.zeros((height, width, 3))
    for cells, amp in ((4, 0.35), (16, 0.2), (64, 0.1)):
        small = rng.random((cells * height // width + 1, cells, 3))
        layers += amp * cv2.resize(small, (width, height), interpolation=cv2.INTER_CUBIC)
    return np.clip(layers / 0.65, 0.0, 1.0)


def synthesize(
    mesh: Mesh,
    camera: Camera,
    *,
    lighting: Lighting = LIGHTINGS["front"],
    renderer: Renderer | None = None,
    noise: float = 0.01,
    seed: int = 0,
) -> tuple[npt.NDArray[np.uint8], npt.NDArray[np.bool_]]:
    """A photo (H, W, 3) uint8 RGB of the mesh at ``camera`` and its true mask (H, W) bool."""
    r = renderer if renderer is not None else Renderer()
    frame = r.render(mesh, camera)
    mask = frame.coverage
    attrs = frame.full(np.where(frame.labels[..., None] > 0, frame.attrs, 0.0)).astype(np.float64)
    light = np.asarray(lighting.direction, np.float64)
    light /= np.linalg.norm(light)
    # Normals face the camera (n_z < 0); the light direction points from the surface to the light.
    lambert = attrs[..., 1:] @ light
    colour = (
        attrs[..., :1] * np.asarray(lighting.ambient)
        + lambert[..., None] * np.asarray(lighting.diffuse)
        + lighting.offset
    )
    if lighting.negative:
        colour = 1.0 - colour
    rng = np.random.default_rng(seed)
    img = _background(camera.height, camera.width, rng)
    img[mask] = colour[mask]
    img += rng.normal(0.0, noise, img.shape)
    return (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8), mask



def random_framed_view(
    model: VehicleModel, rng: np.random.Generator, width: int, height: int
) -> tuple[Camera, dict[str, float]]:
    """A random camera that shows the whole vehicle: azimuth 0-360, elevation 3-30 degrees,
    focal length 0.8-2.5 image widths, the vehicle 40-80 % of the image width, a little off
    centre. Returns the camera and its view parameters."""
    from .initialize import view_camera

    az, el = float(rng.uniform(0, 360)), float(rng.uniform(3, 30))
    focal = float(rng.uniform(0.8, 2.5)) * width
    frac = float(rng.uniform(0.4, 0.8))
    cx = width / 2 + rng.uniform(-0.08, 0.08) * width
    cy = height / 2 + rng.uniform(-0.08, 0.08) * height
    cam = view_camera(model, az, el, 0.0, (cx - 1, cy - 1, cx + 1, cy + 1), width, height, focal)
    uv = cam.project(model.mesh.vertices)
    aspect = (uv[:, 1].max() - uv[:, 1].min()) / max(uv[:, 0].max() - uv[:, 0].min(), 1e-9)
    bw = frac * width
    bh = min(bw * aspect, 0.85 * height)
    bw = bh / aspect
    box = (cx - bw / 2, cy - bh / 2, cx + bw / 2, cy + bh / 2)
    cam = view_camera(model, az, el, 0.0, box, width, height, focal)
    return cam, {"azimuth": az, "elevation": el, "focal": focal, "width_fraction": bw / width}
