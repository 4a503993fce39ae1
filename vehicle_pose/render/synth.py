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

from vehicle_pose.geometry.camera import Camera
from vehicle_pose.model.library import VehicleModel
from vehicle_pose.model.mesh import KINDS, Mesh
from vehicle_pose.render.renderer import Renderer

__all__ = ["Lighting", "LIGHTINGS", "HAZARDS", "synthesize", "synthesize_hazard", "border_crop_camera",
           "random_framed_view", "background"]


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


def _smooth_texture(height: int, width: int, rng: np.random.Generator, cells: int,
                    channels: int = 1) -> npt.NDArray[np.float64]:
    """Random values on a grid ``cells`` wide, cubically interpolated to (height, width[, channels])."""
    shape = (cells * height // width + 1, cells) + ((channels,) if channels > 1 else ())
    out: npt.NDArray[np.float64] = cv2.resize(rng.random(shape), (width, height), interpolation=cv2.INTER_CUBIC)
    return out


def background(height: int, width: int, rng: np.random.Generator) -> npt.NDArray[np.float64]:
    """A random textured background (height, width, 3) in [0, 1]: smooth noise at three scales."""
    layers = np.zeros((height, width, 3))
    for cells, amp in ((4, 0.35), (16, 0.2), (64, 0.1)):
        layers += amp * _smooth_texture(height, width, rng, cells, 3)
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
    img = background(camera.height, camera.width, rng)
    img[mask] = colour[mask]
    img += rng.normal(0.0, noise, img.shape)
    return (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8), mask


HAZARDS: tuple[str, ...] = ("mirror-floor", "sky-on-glass", "second-car", "border-crop", "specular", "mirror-paint")
"""What real photos have and :func:`synthesize` lacks, one at a time (:func:`synthesize_hazard`)."""


def synthesize_hazard(
    mesh: Mesh,
    camera: Camera,
    hazard: str,
    *,
    lighting: Lighting = LIGHTINGS["front"],
    renderer: Renderer | None = None,
    seed: int = 0,
) -> tuple[npt.NDArray[np.uint8], npt.NDArray[np.bool_], Camera]:
    """A synthetic photo with one difficulty of real photos, the vehicle's true mask and its
    true camera.

    ``hazard`` is one of :data:`HAZARDS`:

    - ``mirror-floor``: the vehicle's mirror image below it, dimmed, as on a polished floor;
    - ``sky-on-glass``: a bright cloudy sky over every glass pixel instead of its shading;
    - ``second-car``: a second copy of the mesh, turned and differently lit, partly behind it;
    - ``border-crop``: the image moved sideways so that the photo's right border cuts 15 %
      of the vehicle's width (:func:`border_crop_camera`; the true camera returned is the
      moved one);
    - ``specular``: a sharp white highlight of the light on the paint, saturated;
    - ``mirror-paint``: every panel and window a mirror of a random surrounding (a smooth random
      environment looked up by the reflected viewing ray) over a weak diffuse shading, as
      glossy paint shows the sky, buildings and ground around a real car. No lighting of the
      model's normals explains it: the invariant loss is far from credible.
    """
    if hazard not in HAZARDS:
        raise ValueError(f"unknown hazard {hazard!r}; choose one of {', '.join(HAZARDS)}")
    r = renderer if renderer is not None else Renderer()
    rng = np.random.default_rng(seed + 1000)
    if hazard == "border-crop":
        cropped = border_crop_camera(mesh, camera)
        return (*synthesize(mesh, cropped, lighting=lighting, renderer=r, seed=seed), cropped)
    photo, mask = synthesize(mesh, camera, lighting=lighting, renderer=r, seed=seed)
    img = photo.astype(np.float64) / 255.0
    if hazard == "mirror-floor":
        bottom = int(np.flatnonzero(mask.any(axis=1)).max())
        # Row y below the bottom row shows row 2 * bottom - y of the vehicle.
        rows = np.arange(camera.height)
        src = 2 * bottom - rows
        ok = (rows > bottom) & (src >= 0)
        mirror_img = np.zeros_like(img)
        mirror_mask = np.zeros_like(mask)
        mirror_img[ok] = img[src[ok]]
        mirror_mask[ok] = mask[src[ok]]
        img[mirror_mask] = 0.55 * mirror_img[mirror_mask] + 0.45 * img[mirror_mask]
    elif hazard == "sky-on-glass":
        frame = r.render(mesh, camera)
        glass = frame.full(frame.labels == KINDS.index("glass") + 1)
        gradient = np.linspace(0.75, 0.98, camera.height)[:, None]
        sky = gradient + 0.25 * (_smooth_texture(camera.height, camera.width, rng, 8) - 0.5)
        tint = np.array([0.85, 0.92, 1.0])
        img[glass] = np.clip(sky[glass][:, None] * tint, 0.0, 1.0)
    elif hazard == "second-car":
        c = mesh.sphere[0]
        depth = float((camera.R @ c + camera.t)[2])
        # Behind and to one side: the other car stands 1.6 sphere radii further away, shifted
        # by about three quarters of its projected width, turned 40 degrees about the camera's vertical axis.
        angle = np.radians(40.0 if rng.random() < 0.5 else -40.0)
        turn = np.array([[np.cos(angle), 0.0, np.sin(angle)], [0.0, 1.0, 0.0], [-np.sin(angle), 0.0, np.cos(angle)]])
        R2 = turn @ camera.R
        side = 1.0 if rng.random() < 0.5 else -1.0
        centre2 = np.array([side * 1.5 * mesh.sphere[1], 0.0, depth + 1.6 * mesh.sphere[1]])
        t2 = centre2 - R2 @ c
        other = Camera(camera.K, R2, t2, camera.width, camera.height)
        other_photo, other_mask = synthesize(mesh, other, lighting=LIGHTINGS["side"], renderer=r, seed=seed + 1)
        behind = other_mask & ~mask
        img[behind] = other_photo[behind].astype(np.float64) / 255.0
    elif hazard == "specular":
        frame = r.render(mesh, camera)
        attrs = frame.full(np.where(frame.labels[..., None] > 0, frame.attrs, 0.0)).astype(np.float64)
        n = attrs[..., 1:] / np.maximum(attrs[..., :1], 1e-9)
        light = np.asarray(lighting.direction, np.float64)
        light /= np.linalg.norm(light)
        # Blinn-Phong with the viewer on the -z axis of the camera frame (normals face it).
        half = light + np.array([0.0, 0.0, -1.0])
        half /= np.linalg.norm(half)
        spec = np.clip(n @ half, 0.0, 1.0) ** 16
        body = frame.full(frame.labels == KINDS.index("body") + 1)
        img[body] += 1.5 * spec[body][:, None]
    elif hazard == "mirror-paint":
        frame = r.render(mesh, camera)
        attrs = frame.full(np.where(frame.labels[..., None] > 0, frame.attrs, 0.0)).astype(np.float64)
        n = attrs[..., 1:] / np.maximum(np.linalg.norm(attrs[..., 1:], axis=-1, keepdims=True), 1e-9)
        # Each pixel's viewing ray reflected about the normal; its direction picks the
        # environment's texel: a bright sky above a horizon (image y points down), buildings
        # standing on it, dark ground below, as a street around a car. A flat panel mirrors a
        # piece of that scene, not one colour.
        ys, xs = np.mgrid[0 : camera.height, 0 : camera.width].astype(np.float64)
        ray = np.stack([(xs - camera.K[0, 2]) / camera.K[0, 0], (ys - camera.K[1, 2]) / camera.K[1, 1],
                        np.ones_like(xs)], axis=-1)
        ray /= np.linalg.norm(ray, axis=-1, keepdims=True)
        reflected = ray - 2.0 * np.sum(n * ray, axis=-1, keepdims=True) * n
        size = 128
        up_down = np.linspace(-1.0, 1.0, size)[:, None]  # the reflected ray's y, texel row by row
        horizon = 0.1 * (_smooth_texture(1, size, rng, 4)[0] - 0.5)
        skyline = horizon - 0.5 * (_smooth_texture(1, size, rng, 24)[0] > 0.55)
        env = np.where(up_down < skyline, 0.85 - 0.2 * (up_down + 1.0), 0.35)
        env = np.where(up_down > horizon, 0.08 + 0.1 * _smooth_texture(size, size, rng, 16), env)
        u = np.clip(((reflected[..., 0] + 1.0) * 0.5 * (size - 1)).round().astype(int), 0, size - 1)
        v = np.clip(((reflected[..., 1] + 1.0) * 0.5 * (size - 1)).round().astype(int), 0, size - 1)
        img[mask] = 0.2 * img[mask] + 0.9 * env[v[mask], u[mask]][:, None]
    return (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8), mask, camera


def border_crop_camera(mesh: Mesh, camera: Camera, fraction: float = 0.15) -> Camera:
    """``camera`` with its principal point moved so that the photo's right border cuts
    ``fraction`` of the vehicle's projected width."""
    uv = camera.project(mesh.vertices)
    lo, hi = float(uv[:, 0].min()), float(uv[:, 0].max())
    K = camera.K.copy()
    K[0, 2] += (camera.width - 1) - (hi - fraction * (hi - lo))
    return Camera(K, camera.R, camera.t, camera.width, camera.height)



def random_framed_view(
    model: VehicleModel, rng: np.random.Generator, width: int, height: int
) -> tuple[Camera, dict[str, float]]:
    """A random camera that shows the whole vehicle: azimuth 0-360, elevation 3-30 degrees,
    focal length 0.8-2.5 image widths, the vehicle 40-80 % of the image width, a little off
    centre. Returns the camera and its view parameters."""
    from vehicle_pose.search.views import view_camera

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
