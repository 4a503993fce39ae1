"""Edge alignment: a directional chamfer distance from the rendered model's edges to the photo's.

The invariant loss scores how well some lighting of the model's normals explains the photo's
pixels. On real photos much of a car is not explained by any such lighting (sky and buildings
mirrored in the paint and the glass, a car's inside seen through its windows), and what is left
to place the model is where its structure shows: the outline, the window frames, the lights,
the wheel arches. This term measures that directly, as edge-based trackers of textureless
objects do (a directional chamfer, as in D2CO, Imperoli and Pretto 2015):

- the photo's edges: Canny on the blurred luminance; for each of 8 orientations (the gradient's
  direction modulo pi) a distance transform to the edge pixels within one orientation bin;
- the model's edges, per rendered frame: covered pixels where the coverage, the albedo (a
  material boundary) or the normal (a crease) changes, with the orientation of that change;
- the cost: the mean over the model's edge pixels of the distance to a photo edge of the same
  orientation, truncated at ``tau`` and divided by it, in [0, 1].

Only the model's edges inside the photo count: beyond the border nothing is known. The cost is
one compiled pass over the read-back window (numba), like the loss's moments.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
from numba import njit

from vehicle_pose.render.renderer import Frame

__all__ = ["PhotoEdges", "photo_edges", "EdgeLoss", "ORIENTATIONS"]

ORIENTATIONS = 8
"""Orientation bins of the gradient direction modulo pi (22.5 degrees each)."""


@dataclass(frozen=True)
class PhotoEdges:
    """Distance transforms of a photo's edges, one per orientation bin.

    Attributes
    ----------
    distance : (ORIENTATIONS, H, W) float32
        Pixels from each pixel to the nearest edge pixel whose gradient direction lies within
        one bin of the bin's own.
    edges : (H, W) bool
        The edge pixels.
    """

    distance: npt.NDArray[np.float32]
    edges: npt.NDArray[np.bool_]


def _orientation_bins(gx: npt.NDArray[np.float32], gy: npt.NDArray[np.float32]) -> npt.NDArray[np.intp]:
    theta = np.mod(np.arctan2(gy, gx), np.pi)
    return np.minimum((theta / np.pi * ORIENTATIONS).astype(np.intp), ORIENTATIONS - 1)


def photo_edges(rgb: npt.NDArray[np.uint8], *, low: float = 40.0, high: float = 100.0,
                within: npt.NDArray[np.bool_] | None = None) -> PhotoEdges:
    """The edges of an (H, W, 3) uint8 RGB photo and their directional distance transforms.

    ``low`` and ``high`` are Canny's hysteresis thresholds on the 3x3 Sobel gradient of the
    luminance (0-255) after a 3x3 Gaussian blur. With ``within`` (H, W), only the edges there
    count.
    """
    gray = cv2.GaussianBlur(cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY), (3, 3), 0)
    edges = cv2.Canny(gray, low, high) > 0
    if within is not None:
        edges &= within
    gx = cv2.Sobel(gray, cv2.CV_32F, 1, 0)
    gy = cv2.Sobel(gray, cv2.CV_32F, 0, 1)
    bins = _orientation_bins(gx, gy)
    h, w = gray.shape
    far = np.float32(np.hypot(h, w))
    distance = np.empty((ORIENTATIONS, h, w), np.float32)
    for k in range(ORIENTATIONS):
        near = edges & ((bins == k) | (bins == (k + 1) % ORIENTATIONS) | (bins == (k - 1) % ORIENTATIONS))
        if near.any():
            distance[k] = cv2.distanceTransform((~near).astype(np.uint8), cv2.DIST_L2, 3)
        else:
            distance[k] = far
    return PhotoEdges(distance, edges)


@njit(cache=True, nogil=True)
def _edge_cost(labels: npt.NDArray[Any], attrs: npt.NDArray[Any], distance: npt.NDArray[Any], x0: int, y0: int,
               tau: float, albedo_step: float, crease: float) -> tuple[float, int]:  # pragma: no cover - compiled
    h, w = labels.shape
    bins, height, width = distance.shape
    # Channels with a one-pixel border: coverage, albedo and the normal's x and y. Beyond the
    # window the model is absent (0), except where the window meets the photo's border:
    # beyond the photo nothing is known, so the border pixel is repeated (no edge across it).
    ch = np.zeros((h + 2, w + 2, 4), np.float32)
    for r in range(h):
        for c in range(w):
            if labels[r, c] == 0:
                continue
            k = attrs[r, c, 0]
            ch[r + 1, c + 1, 0] = 1.0
            ch[r + 1, c + 1, 1] = k
            if k > 1e-6:
                ch[r + 1, c + 1, 2] = attrs[r, c, 1] / k
                ch[r + 1, c + 1, 3] = attrs[r, c, 2] / k
    if x0 == 0:
        ch[:, 0, :] = ch[:, 1, :]
    if x0 + w >= width:
        ch[:, w + 1, :] = ch[:, w, :]
    if y0 == 0:
        ch[0, :, :] = ch[1, :, :]
    if y0 + h >= height:
        ch[h + 1, :, :] = ch[h, :, :]
    inv = np.empty(4, np.float32)
    inv[0] = 1.0 / (8.0 * 0.5)
    inv[1] = 1.0 / (8.0 * albedo_step)
    inv[2] = 1.0 / (8.0 * crease)
    inv[3] = inv[2]
    total = 0.0
    count = 0
    for r in range(h):
        for c in range(w):
            if labels[r, c] == 0:
                continue
            best = 0.0
            bgx = 0.0
            bgy = 0.0
            for q in range(4):
                gx = (ch[r, c + 2, q] - ch[r, c, q]) + 2.0 * (ch[r + 1, c + 2, q] - ch[r + 1, c, q]) \
                    + (ch[r + 2, c + 2, q] - ch[r + 2, c, q])
                gy = (ch[r + 2, c, q] - ch[r, c, q]) + 2.0 * (ch[r + 2, c + 1, q] - ch[r, c + 1, q]) \
                    + (ch[r + 2, c + 2, q] - ch[r, c + 2, q])
                m = (gx * gx + gy * gy) * inv[q] * inv[q]
                if m > best:
                    best = m
                    bgx = gx
                    bgy = gy
            if best < 0.25:
                continue
            theta = np.arctan2(bgy, bgx)
            if theta < 0.0:
                theta += np.pi
            b = int(theta / np.pi * bins)
            if b >= bins:
                b = bins - 1
            d = distance[b, r + y0, c + x0]
            total += d if d < tau else tau
            count += 1
    return total, count


class EdgeLoss:
    """The directional chamfer cost of a rendered frame against one photo, in [0, 1].

    Parameters
    ----------
    rgb : (H, W, 3) uint8
        The photo at the frame's size.
    tau : float, keyword-only
        Truncation of the distance, as a fraction of the photo's diagonal: a model edge
        further than this from any photo edge of its orientation costs 1.
    albedo_step : float, keyword-only
        Change of albedo between neighbouring pixels that makes a material edge.
    crease : float, keyword-only
        Change of a camera-space normal component between neighbouring pixels that makes a
        crease (0.6: about 35 degrees).
    min_pixels : int, keyword-only
        A frame with fewer edge pixels costs 1.
    foreground : (H, W) bool, keyword-only
        Where the vehicle is believed to be: only the photo's edges within ``reach`` of it
        (a fraction of the diagonal) count, so that a parked car or a floor's reflection
        beyond the mask cannot hold the model's outline.
    """

    def __init__(self, rgb: npt.NDArray[np.uint8], *, tau: float = 0.03, albedo_step: float = 0.08,
                 crease: float = 0.6, min_pixels: int = 8,
                 foreground: npt.NDArray[np.bool_] | None = None, reach: float = 0.03) -> None:
        if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3 or min(rgb.shape[:2]) < 2:
            raise ValueError(f"the edge term needs an (H, W, 3) uint8 photo, got {rgb.dtype} {rgb.shape}")
        h, w = rgb.shape[:2]
        within = None
        if foreground is not None and not foreground.all():
            r = max(1, round(reach * float(np.hypot(h, w))))
            within = cv2.dilate(foreground.astype(np.uint8),
                                cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))) > 0
        self.edges = photo_edges(rgb, within=within)
        self.tau = max(2.0, tau * float(np.hypot(h, w)))
        self.albedo_step = albedo_step
        self.crease = crease
        self.min_pixels = min_pixels

    def __call__(self, frame: Frame) -> float:
        if frame.labels.size == 0:
            return 1.0
        total, count = _edge_cost(frame.labels, frame.attrs, self.edges.distance, int(frame.x0), int(frame.y0),
                                  float(self.tau), float(self.albedo_step), float(self.crease))
        if count < self.min_pixels:
            return 1.0
        return float(total / count / self.tau)
