"""Finding the vehicle in a photo without any hint (issue: no-hint registration, step 1).

A claims photo is about the vehicle: it is large and roughly central. GrabCut starts from a
rectangle a little inside the photo's border, then runs again seeded by its own first answer
(the largest connected component with its holes filled, grown as probable background, shrunk
as certain foreground). The result is the vehicle's mask and box, used by the wheel detector,
the view search and the credibility check of the final pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from vehicle_pose.clock import timed
from vehicle_pose.photo import resized
from vehicle_pose.segment.grabcut import disk

__all__ = ["VehicleRegion", "find_vehicle", "largest_component"]

Box = tuple[float, float, float, float]


@dataclass(frozen=True)
class VehicleRegion:
    """The vehicle's pixels (H, W) bool at the photo's size and their box X0, Y0, X1, Y1."""

    mask: npt.NDArray[np.bool_]
    box: Box

    @property
    def area_fraction(self) -> float:
        """Share of the photo covered by the region."""
        return float(self.mask.mean())

    @classmethod
    def from_mask(cls, mask: npt.NDArray[np.bool_]) -> VehicleRegion:
        """The region of a known mask (an empty mask gives the whole photo)."""
        mask = mask.astype(bool)
        if not mask.any():
            mask = np.ones_like(mask)
        ys, xs = np.nonzero(mask)
        return cls(mask, (float(xs.min()), float(ys.min()), float(xs.max()), float(ys.max())))

    def resized(self, width: int, height: int) -> VehicleRegion:
        """The region for the photo resized to ``width`` x ``height``."""
        H, W = self.mask.shape
        mask = cv2.resize(self.mask.astype(np.uint8), (width, height), interpolation=cv2.INTER_NEAREST) > 0
        sx, sy = width / W, height / H
        x0, y0, x1, y1 = self.box
        return VehicleRegion(mask, (x0 * sx, y0 * sy, x1 * sx, y1 * sy))


def largest_component(mask: npt.NDArray[np.bool_]) -> npt.NDArray[np.bool_]:
    """The largest 8-connected component of ``mask`` with its holes filled."""
    m = mask.astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    if n <= 1:
        return mask.astype(bool)
    keep = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    comp = (labels == keep).astype(np.uint8)
    contours, _ = cv2.findContours(comp, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    filled = np.zeros_like(comp)
    cv2.drawContours(filled, contours, -1, 1, thickness=cv2.FILLED)
    out: npt.NDArray[np.bool_] = filled.astype(bool)
    return out


@timed("grabcut")
def find_vehicle(
    rgb: npt.NDArray[np.uint8],
    *,
    size: int = 320,
    border: tuple[float, float] = (0.08, 0.1),
    iterations: int = 5,
    rect: Box | None = None,
) -> VehicleRegion:
    """The vehicle's region in a photo with no hint.

    Parameters
    ----------
    rgb : (H, W, 3) uint8
    size : int, keyword-only
        GrabCut runs on the photo reduced to this longer side
        (docs/decisions/0007-no-hint-search.md).
    border : (fx, fy), keyword-only
        Fractions of the width and height outside the start rectangle (certain background).
    iterations : int, keyword-only
        GrabCut iterations of each pass.
    rect : (X0, Y0, X1, Y1), keyword-only
        The vehicle's box when a client gave one; it replaces the central start rectangle.

    Returns
    -------
    VehicleRegion
        When GrabCut finds nothing usable, the start rectangle itself.
    """
    H, W = rgb.shape[:2]
    s = min(1.0, size / max(W, H))
    w, h = max(16, round(W * s)), max(16, round(H * s))
    small = resized(rgb, w, h)
    bgr = cv2.cvtColor(np.ascontiguousarray(small), cv2.COLOR_RGB2BGR)
    if rect is None:
        bx, by = max(1, round(border[0] * w)), max(1, round(border[1] * h))
        x0, y0, x1, y1 = bx, by, w - bx, h - by
    else:
        x0, y0 = max(0, int(rect[0] * s)), max(0, int(rect[1] * s))
        x1, y1 = min(w, int(np.ceil(rect[2] * s)) + 1), min(h, int(np.ceil(rect[3] * s)) + 1)
    fallback = np.zeros((h, w), bool)
    fallback[y0:y1, x0:x1] = True
    if fallback.all():  # GrabCut needs some background: keep a one-pixel frame
        fallback[[0, -1], :] = fallback[:, [0, -1]] = False
        x0, y0, x1, y1 = max(x0, 1), max(y0, 1), min(x1, w - 1), min(y1, h - 1)

    mask = np.zeros((h, w), np.uint8)
    bgd, fgd = np.zeros((1, 65)), np.zeros((1, 65))
    cv2.setRNGSeed(0)
    cv2.grabCut(bgr, mask, (x0, y0, x1 - x0, y1 - y0), bgd, fgd, iterations, cv2.GC_INIT_WITH_RECT)
    first = largest_component((mask == cv2.GC_FGD) | (mask == cv2.GC_PR_FGD))
    if first.sum() < 0.01 * w * h:
        region = fallback
    else:
        # Second pass seeded by the first answer: its core is certain, a band around it open.
        r = max(2, round(0.04 * float(np.sqrt(first.sum()))))
        grown = cv2.dilate(first.astype(np.uint8), disk(3 * r)).astype(bool)
        core = cv2.erode(first.astype(np.uint8), disk(r)).astype(bool)
        seeded = np.full((h, w), cv2.GC_BGD, np.uint8)
        seeded[grown] = cv2.GC_PR_BGD
        seeded[first] = cv2.GC_PR_FGD
        seeded[core] = cv2.GC_FGD
        if core.any() and (seeded == cv2.GC_BGD).any():
            bgd, fgd = np.zeros((1, 65)), np.zeros((1, 65))
            cv2.grabCut(bgr, seeded, None, bgd, fgd, iterations, cv2.GC_INIT_WITH_MASK)
            second = largest_component((seeded == cv2.GC_FGD) | (seeded == cv2.GC_PR_FGD))
            region = second if second.sum() >= 0.3 * first.sum() else first
        else:
            region = first
    return VehicleRegion.from_mask(cv2.resize(region.astype(np.uint8), (W, H), interpolation=cv2.INTER_NEAREST) > 0)
