"""Start poses from the vehicle's wheels (the seed paper's start, after Hutter & Brewer 2009).

A wheel seen from the side is a dark tyre around a lighter rim: its outline is an ellipse whose
minor axis is the image direction of the axle and whose axis ratio is the cosine of the axle's
angle to the line of sight. Dark blobs of the vehicle region's lower part, at several
darkness levels, are fitted with ellipses and kept when they are elliptical and darker than
their rim and surroundings. Pairs of similar ellipses become start poses theta = (mu, delta,
psi, f = 10 W) on either side and in either order; poses that stand the vehicle on its roof are
dropped, and the rest are scored like the view search's.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from vehicle_pose.errors import PoseError
from vehicle_pose.geometry.camera import Camera
from vehicle_pose.geometry.pose import Theta, theta_to_camera
from vehicle_pose.model.library import VehicleModel
from vehicle_pose.model.metadata import parse_axis
from vehicle_pose.search.views import Candidate
from vehicle_pose.segment.grabcut import disk
from vehicle_pose.segment.region import VehicleRegion

__all__ = ["Ellipse", "detect_wheels", "wheel_candidates"]

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Ellipse:
    """An ellipse in pixels: centre (x, y), semi-axes a >= b, major axis angle (radians)."""

    centre: tuple[float, float]
    a: float
    b: float
    angle: float
    score: float = 0.0

    @property
    def minor_direction(self) -> FloatArray:
        """Unit image direction (2,) of the minor axis."""
        return np.array([-np.sin(self.angle), np.cos(self.angle)])

    def to_dict(self) -> dict[str, object]:
        return {"centre": list(self.centre), "a": self.a, "b": self.b, "angle": self.angle, "score": self.score}


def _ellipse_mask(shape: tuple[int, int], e: Ellipse, scale: float) -> npt.NDArray[np.bool_]:
    m = np.zeros(shape, np.uint8)
    axes = (max(1, round(e.a * scale)), max(1, round(e.b * scale)))
    centre = (round(e.centre[0]), round(e.centre[1]))
    cv2.ellipse(m, centre, axes, float(np.degrees(e.angle)), 0.0, 360.0, 1, thickness=-1)
    return m.astype(bool)


def _ring_contrast(gray: npt.NDArray[np.float32], e: Ellipse) -> float:
    """How much darker the tyre ring is than the rim inside and the surroundings outside."""
    shape = gray.shape
    inner = _ellipse_mask(shape, e, 0.5)
    tyre = _ellipse_mask(shape, e, 0.98) & ~_ellipse_mask(shape, e, 0.72)
    outer = _ellipse_mask(shape, e, 1.35) & ~_ellipse_mask(shape, e, 1.08)
    if not (inner.any() and tyre.any() and outer.any()):
        return -1.0
    t = float(gray[tyre].mean())
    return 0.5 * (float(gray[inner].mean()) - t) + 0.5 * (float(gray[outer].mean()) - t)


def detect_wheels(
    rgb: npt.NDArray[np.uint8],
    region: VehicleRegion,
    *,
    max_count: int = 6,
    work_width: int = 400,
    percentiles: tuple[float, ...] = (6.0, 12.0, 20.0, 30.0),
) -> list[Ellipse]:
    """Wheel-like ellipses in the vehicle's region, best first (photo pixels).

    Parameters
    ----------
    rgb : (H, W, 3) uint8
    region : VehicleRegion
        The vehicle's region; wheels are looked for in and just around it.
    max_count : int, keyword-only
    work_width : int, keyword-only
        The region's box is reduced (or enlarged) to about this width for the search.
    percentiles : tuple of float, keyword-only
        Darkness levels: gray percentiles within the region.
    """
    H, W = rgb.shape[:2]
    x0, y0, x1, y1 = region.box
    bw, bh = x1 - x0, y1 - y0
    if bw < 16 or bh < 16:
        return []
    cx0, cy0 = int(max(0, x0 - 0.05 * bw)), int(max(0, y0 - 0.05 * bh))
    cx1, cy1 = int(min(W, x1 + 0.05 * bw + 1)), int(min(H, y1 + 0.1 * bh + 1))
    k = work_width / max(cx1 - cx0, 1)
    size = (max(8, round((cx1 - cx0) * k)), max(8, round((cy1 - cy0) * k)))
    crop = cv2.resize(rgb[cy0:cy1, cx0:cx1], size, interpolation=cv2.INTER_AREA)
    gray = cv2.GaussianBlur(cv2.cvtColor(crop, cv2.COLOR_RGB2GRAY), (3, 3), 0).astype(np.float32)
    inside = cv2.resize(region.mask[cy0:cy1, cx0:cx1].astype(np.uint8), size, interpolation=cv2.INTER_NEAREST)
    # Only the region itself (grown by a pixel): dark background touching a tyre spoils its outline.
    allowed = cv2.dilate(inside, np.ones((3, 3), np.uint8)) > 0
    if not inside.any():
        return []
    top = (y0 - cy0 + 0.3 * bh) * k  # wheels sit in the lower part of the vehicle
    min_a, max_a = 0.025 * size[0], 0.25 * size[0]
    found: list[Ellipse] = []
    blobs = []
    for p in percentiles:
        thr = float(np.percentile(gray[inside > 0], p))
        dark = ((gray <= thr) & allowed).astype(np.uint8)
        # Openings of growing size cut a tyre loose from the dark wheel arch or shadow it touches.
        for radius in (1, 3, 6):
            opened = cv2.morphologyEx(dark, cv2.MORPH_OPEN, disk(radius))
            blobs += cv2.findContours(opened, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)[0]
    for c in blobs:
        if len(c) < 12:
            continue
        (ex, ey), (d1, d2), ang = cv2.fitEllipse(c)
        a, b = 0.5 * max(d1, d2), 0.5 * min(d1, d2)
        if not (min_a <= a <= max_a) or b < 0.2 * a or ey < top:
            continue
        area = cv2.contourArea(c)
        hull = cv2.contourArea(cv2.convexHull(c))
        fill = area / (np.pi * a * b)
        if not (0.75 <= fill <= 1.2) or hull <= 0 or area / hull < 0.88:
            continue
        angle = np.radians(ang) + (np.pi / 2 if d2 > d1 else 0.0)
        e = Ellipse((ex, ey), a, b, float(angle))
        contrast = _ring_contrast(gray, e)
        if contrast <= 4.0:
            continue
        score = contrast / 255.0 * (1.0 - abs(1.0 - fill)) * area / hull
        found.append(Ellipse((ex, ey), a, b, float(angle), float(score)))
    found.sort(key=lambda e: -e.score)
    kept: list[Ellipse] = []
    for e in found:
        if all(np.hypot(e.centre[0] - q.centre[0], e.centre[1] - q.centre[1]) > 0.6 * max(q.a, e.a) for q in kept):
            kept.append(e)
        if len(kept) == max_count:
            break
    # Back to photo pixels.
    return [
        Ellipse((e.centre[0] / k + cx0, e.centre[1] / k + cy0), e.a / k, e.b / k, e.angle, e.score) for e in kept
    ]


def wheel_candidates(
    ellipses: list[Ellipse],
    model: VehicleModel,
    width: int,
    height: int,
    *,
    focal_widths: float = 10.0,
    tilts: tuple[float, ...] = (12.0, 30.0, 50.0),
) -> list[Candidate]:
    """Start poses from pairs of wheel ellipses (unscored), at the photo's size.

    Each ordered pair of similar ellipses at a plausible distance is taken as (rear, front)
    wheels of the left or the right side, with the axle tilted either way out of the image
    plane (the measured tilt and each of ``tilts``, degrees); poses that do not keep the
    vehicle upright (up within 60 degrees of image up) are dropped.
    """
    wheels = model.wheels
    up = parse_axis(model.info.up)
    ratio = float(np.linalg.norm(wheels.front_axle_center - wheels.rear_axle_center)) / wheels.wheel_radius
    out: list[Candidate] = []
    for (i, e1), (j, e2) in itertools.permutations(enumerate(ellipses), 2):
        a = 0.5 * (e1.a + e2.a)
        if not 0.6 <= e1.a / e2.a <= 1.0 / 0.6:
            continue
        d = np.array(e2.centre) - np.array(e1.centre)
        dist = float(np.linalg.norm(d))
        if not 1.2 * a <= dist <= 1.3 * ratio * a or abs(d[1]) > 0.7 * abs(d[0]) + 1e-9:
            continue
        # The axis ratio gives the axle's tilt out of the image plane, but a tyre's tread and
        # the arch above it bias it; a few fixed tilts are tried beside the measured one, with
        # the axle's image direction along the ellipses' minor axis and along the wheel line.
        q = float(np.clip(0.5 * (e1.b / e1.a + e2.b / e2.a), 0.05, 0.999))
        m1, m2 = e1.minor_direction, e2.minor_direction
        m = m1 + (m2 if m1 @ m2 >= 0 else -m2)
        m /= np.linalg.norm(m)
        axes = [(float(np.arccos(q)), m)] + [(float(np.radians(t)), d / dist) for t in tilts]
        for (tilt, direction), sign in itertools.product(axes, (1.0, -1.0)):
            psi = np.array([*(sign * np.sin(tilt) * direction), -np.cos(tilt)])
            for side in ("left", "right"):
                theta = Theta(np.array(e1.centre), d, psi, focal_widths * width, side)
                try:
                    cam: Camera = theta_to_camera(theta, wheels.side(side), width, height)
                except PoseError:
                    continue
                if float((cam.R @ up)[1]) > -0.5:
                    continue
                out.append(Candidate(cam, "wheels",
                                     detail={"rear": i, "front": j, "tilt": float(sign * np.degrees(tilt)),
                                                            "left_side": float(side == "left")}))
    return out
