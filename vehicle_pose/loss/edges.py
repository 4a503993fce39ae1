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

from vehicle_pose.clock import timed
from vehicle_pose.render.renderer import Frame

__all__ = ["PhotoEdges", "photo_edges", "model_edges", "EdgeLoss", "TwoWayChamfer", "ORIENTATIONS"]

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
    bins : (H, W) int8
        The orientation bin of each edge pixel's gradient, -1 off the edges.
    """

    distance: npt.NDArray[np.float32]
    edges: npt.NDArray[np.bool_]
    bins: npt.NDArray[np.int8]


def _orientation_bins(gx: npt.NDArray[np.float32], gy: npt.NDArray[np.float32]) -> npt.NDArray[np.intp]:
    theta = np.mod(np.arctan2(gy, gx), np.pi)
    return np.minimum((theta / np.pi * ORIENTATIONS).astype(np.intp), ORIENTATIONS - 1)


@timed("photo edges")
def photo_edges(rgb: npt.NDArray[np.uint8], *, low: float = 40.0, high: float = 100.0,
                within: npt.NDArray[np.bool_] | None = None, colour: bool = False) -> PhotoEdges:
    """The edges of an (H, W, 3) uint8 RGB photo and their directional distance transforms.

    ``low`` and ``high`` are Canny's hysteresis thresholds on the 3x3 Sobel gradient of the
    luminance (0-255) after a 3x3 Gaussian blur; with ``colour``, of whichever of the three
    colour channels changes most at each pixel (as LINE-2D takes its gradients), so that a red
    lamp on dark paint, of nearly the same luminance, has an outline. With ``within`` (H, W),
    only the edges there count.
    """
    if colour:
        blurred = cv2.GaussianBlur(np.ascontiguousarray(rgb), (3, 3), 0)
        gxs = np.stack([cv2.Sobel(blurred[..., k], cv2.CV_16S, 1, 0) for k in range(3)])
        gys = np.stack([cv2.Sobel(blurred[..., k], cv2.CV_16S, 0, 1) for k in range(3)])
        strongest = np.argmax(gxs.astype(np.int32) ** 2 + gys.astype(np.int32) ** 2, axis=0)[None]
        dx = np.ascontiguousarray(np.take_along_axis(gxs, strongest, 0)[0])
        dy = np.ascontiguousarray(np.take_along_axis(gys, strongest, 0)[0])
        edges = cv2.Canny(dx, dy, low, high) > 0
        gx, gy = dx.astype(np.float32), dy.astype(np.float32)
    else:
        gray = cv2.GaussianBlur(cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY), (3, 3), 0)
        edges = cv2.Canny(gray, low, high) > 0
        gx = cv2.Sobel(gray, cv2.CV_32F, 1, 0)
        gy = cv2.Sobel(gray, cv2.CV_32F, 0, 1)
    if within is not None:
        edges &= within
    bins = _orientation_bins(gx, gy)
    h, w = edges.shape
    far = np.float32(np.hypot(h, w))
    distance = np.empty((ORIENTATIONS, h, w), np.float32)
    for k in range(ORIENTATIONS):
        near = edges & ((bins == k) | (bins == (k + 1) % ORIENTATIONS) | (bins == (k - 1) % ORIENTATIONS))
        if near.any():
            distance[k] = cv2.distanceTransform((~near).astype(np.uint8), cv2.DIST_L2, 3)
        else:
            distance[k] = far
    return PhotoEdges(distance, edges, np.where(edges, bins, -1).astype(np.int8))


@njit(cache=True, nogil=True)
def _model_edges(labels: npt.NDArray[Any], attrs: npt.NDArray[Any], x0: int, y0: int, width: int, height: int,
                 albedo_step: float, crease: float) -> npt.NDArray[np.int8]:  # pragma: no cover - compiled
    """The orientation bin of the model's edge at each pixel of a rendered window, -1 where there
    is none: covered pixels where the coverage, the albedo or the normal changes."""
    h, w = labels.shape
    bins = ORIENTATIONS
    # Channels with a one-pixel border: coverage, albedo and the normal's x and y. Beyond the
    # window the model is absent (0), except where the window meets the photo's border:
    # beyond the photo nothing is known, so the border pixel is repeated (no edge across it).
    ch = np.zeros((4, h + 2, w + 2), np.float32)
    for r in range(h):
        for c in range(w):
            if labels[r, c] == 0:
                continue
            k = attrs[r, c, 0]
            ch[0, r + 1, c + 1] = 1.0
            ch[1, r + 1, c + 1] = k
            if k > 1e-6:
                ch[2, r + 1, c + 1] = attrs[r, c, 1] / k
                ch[3, r + 1, c + 1] = attrs[r, c, 2] / k
    if x0 == 0:
        ch[:, :, 0] = ch[:, :, 1]
    if x0 + w >= width:
        ch[:, :, w + 1] = ch[:, :, w]
    if y0 == 0:
        ch[:, 0, :] = ch[:, 1, :]
    if y0 + h >= height:
        ch[:, h + 1, :] = ch[:, h, :]
    inv = np.empty(4, np.float32)
    inv[0] = 1.0 / (8.0 * 0.5)
    inv[1] = 1.0 / (8.0 * albedo_step)
    inv[2] = 1.0 / (8.0 * crease)
    inv[3] = inv[2]
    out = np.full((h, w), -1, np.int8)
    # Row by row, each channel's Sobel response over the whole row (a loop without branches
    # that the compiler vectorises), the strongest channel's kept per pixel.
    best = np.empty(w, np.float64)
    bgx = np.empty(w, np.float64)
    bgy = np.empty(w, np.float64)
    for r in range(h):
        best[:] = 0.0
        bgx[:] = 0.0
        bgy[:] = 0.0
        for q in range(4):
            above, row, below = ch[q, r], ch[q, r + 1], ch[q, r + 2]
            for c in range(w):
                gx = (above[c + 2] - above[c]) + 2.0 * (row[c + 2] - row[c]) + (below[c + 2] - below[c])
                gy = (below[c] - above[c]) + 2.0 * (below[c + 1] - above[c + 1]) + (below[c + 2] - above[c + 2])
                m = (gx * gx + gy * gy) * inv[q] * inv[q]
                if m > best[c]:
                    best[c] = m
                    bgx[c] = gx
                    bgy[c] = gy
        for c in range(w):
            if labels[r, c] == 0 or best[c] < 0.25:
                continue
            theta = np.arctan2(bgy[c], bgx[c])
            if theta < 0.0:
                theta += np.pi
            b = int(theta / np.pi * bins)
            if b >= bins:
                b = bins - 1
            out[r, c] = b
    return out


@njit(cache=True, nogil=True)
def _forward_cost(edges: npt.NDArray[np.int8], distance: npt.NDArray[Any], x0: int, y0: int,
                  tau: float) -> tuple[float, int]:  # pragma: no cover - compiled
    """The sum over the model's edge pixels of the distance to a photo edge of their bin,
    truncated at ``tau``, and their count."""
    h, w = edges.shape
    total = 0.0
    count = 0
    for r in range(h):
        for c in range(w):
            b = edges[r, c]
            if b < 0:
                continue
            d = distance[b, r + y0, c + x0]
            total += d if d < tau else tau
            count += 1
    return total, count


@njit(cache=True, nogil=True)
def _binned_cells(edges: npt.NDArray[np.int8], dx: int, dy: int, h2: int, w2: int
                  ) -> npt.NDArray[np.uint8]:  # pragma: no cover - compiled
    """(ORIENTATIONS, h2, w2) uint8: 0 in the half-resolution cells holding a model edge pixel
    whose bin is within one of the plane's bin (``edges`` placed at ``dx``, ``dy`` of a grid
    of cells of two pixels), 1 elsewhere (what a distance transform measures from)."""
    out = np.ones((ORIENTATIONS, h2, w2), np.uint8)
    h, w = edges.shape
    for r in range(h):
        for c in range(w):
            b = edges[r, c]
            if b < 0:
                continue
            rr, cc = (r + dy) // 2, (c + dx) // 2
            if rr >= h2 or cc >= w2:
                continue
            out[b, rr, cc] = 0
            out[(b + 1) % ORIENTATIONS, rr, cc] = 0
            out[(b + ORIENTATIONS - 1) % ORIENTATIONS, rr, cc] = 0
    return out


@njit(cache=True, nogil=True)
def _reverse_cost(rows: npt.NDArray[np.int32], cols: npt.NDArray[np.int32], bins: npt.NDArray[np.int8],
                  near: npt.NDArray[np.float32], x0: int, y0: int, tau: float) -> float:  # pragma: no cover
    """The sum over the photo's edge pixels (``rows``, ``cols``, ``bins``) of the distance to the
    model's nearest edge of their bin (``near``: per bin, over the window at ``x0``, ``y0``;
    beyond it the distance is at least ``tau``), truncated at ``tau``."""
    _, h, w = near.shape
    total = 0.0
    for i in range(rows.size):
        r = rows[i] - y0
        c = cols[i] - x0
        if r < 0 or c < 0 or r >= h or c >= w:
            total += tau
            continue
        d = near[bins[i], r, c]
        total += d if d < tau else tau
    return total


def model_edges(frame: Frame, *, albedo_step: float = 0.08, crease: float = 0.6) -> npt.NDArray[np.int8]:
    """(h, w) int8: the orientation bin of the model's edge at each pixel of the frame's window
    (-1 where there is none): where the coverage, the albedo (by ``albedo_step``) or a
    camera-space normal component (by ``crease``, 0.6 is about 35 degrees) changes between
    neighbouring pixels. The window's sides on the photo's border make no edge."""
    if frame.labels.size == 0:
        return np.zeros((0, 0), np.int8)
    out: npt.NDArray[np.int8] = _model_edges(frame.labels, frame.attrs, int(frame.x0), int(frame.y0), frame.width,
                                             frame.height, float(albedo_step), float(crease))
    return out


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

    @timed("chamfer")
    def __call__(self, frame: Frame) -> float:
        if frame.labels.size == 0:
            return 1.0
        edges = model_edges(frame, albedo_step=self.albedo_step, crease=self.crease)
        total, count = _forward_cost(edges, self.edges.distance, int(frame.x0), int(frame.y0), float(self.tau))
        if count < self.min_pixels:
            return 1.0
        return float(total / count / self.tau)


class TwoWayChamfer:
    """The model's edges against the photo's and the photo's against the model's, in [0, 2].

    The directional chamfer of :class:`EdgeLoss` asks only whether the model's edges lie on
    edges of the photo. On a real photo edges are everywhere (every reflection makes one), and a
    wrong pose whose outline matches finds something for its inner edges too: half a turn away a
    car's outline is nearly the same, and the chamfer alone prefers that twin on most real
    photos (``docs/decisions/0020-view-sphere-search.md``). The converse asks whether the
    photo's edges in the vehicle's box lie on edges of the model: the grille, the lamps and the
    window frames of the photo are left unexplained by the twin. The sum of both directions is
    the symmetric chamfer distance of the two edge sets, as edge-based template matching scores
    a match (the oriented chamfer of Shotton et al., and its two-way form in FDCM's
    verification, Liu et al. 2010).

    The converse counts the photo's edges inside ``region`` only, a box that does not depend on
    the pose (the client's box, the photo's frame, the region a search is placing the model
    in): counted inside the model's own silhouette, a model shrunk onto a clean panel explains
    all the edges it keeps.

    Parameters
    ----------
    rgb : (H, W, 3) uint8
        The photo at the frames' size.
    region : (X0, Y0, X1, Y1), optional, keyword-only
        The photo's edges counted by the converse (pixels); the whole photo by default.
    tau : float, keyword-only
        Truncation of both distances, as a fraction of the photo's diagonal.
    albedo_step, crease, min_pixels : keyword-only
        As for :class:`EdgeLoss`.
    colour : bool, keyword-only
        The photo's edges from its colour channels (:func:`photo_edges`).
    edges : PhotoEdges, keyword-only
        The photo's edges, when already found (several regions of one photo).
    """

    def __init__(self, rgb: npt.NDArray[np.uint8], *, region: tuple[float, float, float, float] | None = None,
                 tau: float = 0.05, albedo_step: float = 0.08, crease: float = 0.6, min_pixels: int = 8,
                 colour: bool = False, edges: PhotoEdges | None = None,
                 among: tuple[float, float, float, float] | None = None, clutter: float = 1.0) -> None:
        if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3 or min(rgb.shape[:2]) < 2:
            raise ValueError(f"the edge term needs an (H, W, 3) uint8 photo, got {rgb.dtype} {rgb.shape}")
        h, w = rgb.shape[:2]
        self.edges = edges if edges is not None else photo_edges(rgb, colour=colour)
        self.tau = max(2.0, tau * float(np.hypot(h, w)))
        self.albedo_step, self.crease, self.min_pixels = albedo_step, crease, min_pixels
        def within(b: tuple[float, float, float, float] | None) -> npt.NDArray[np.bool_]:
            out = self.edges.edges.copy()
            if b is not None:
                x0, y0 = max(0, int(np.floor(b[0]))), max(0, int(np.floor(b[1])))
                x1, y1 = min(w - 1, int(np.ceil(b[2]))), min(h - 1, int(np.ceil(b[3])))
                box = np.zeros_like(out)
                box[y0:y1 + 1, x0:x1 + 1] = True
                out &= box
            return out

        inside = within(region)
        # The photo's edges among the regions compared but outside this one: explained by the
        # clutter, each at the cost ``clutter``.
        self.outside = int((within(among) & ~inside).sum()) if among is not None else 0
        self.clutter = float(clutter)
        rows, cols = np.nonzero(inside)
        self.rows, self.cols = rows.astype(np.int32), cols.astype(np.int32)
        self.photo_bins = self.edges.bins[rows, cols].astype(np.int8)

    @timed("chamfer")
    def parts(self, frame: Frame) -> tuple[float, float]:
        """The forward and the converse cost of a rendered frame, each in [0, 1]."""
        if frame.labels.size == 0:
            return 1.0, 1.0
        x0, y0 = int(frame.x0), int(frame.y0)
        model = model_edges(frame, albedo_step=self.albedo_step, crease=self.crease)
        total, count = _forward_cost(model, self.edges.distance, x0, y0, float(self.tau))
        if count < self.min_pixels:
            return 1.0, 1.0
        forward = float(total / count / self.tau)
        if self.rows.size == 0:
            return forward, 1.0 if self.outside == 0 else self.clutter
        # The model's edges per orientation bin (within one bin, as for the photo's), on a grid
        # of half the resolution (a cell holds a bin when one of its pixels does): their distance
        # transforms over the window grown by the truncation cost a quarter, and a distance is
        # off by at most a pixel, far below the truncation.
        pad = int(np.ceil(self.tau)) + 2
        h, w = model.shape
        gx0, gy0 = max(0, x0 - pad) & ~1, max(0, y0 - pad) & ~1
        gx1, gy1 = min(frame.width, x0 + w + pad), min(frame.height, y0 + h + pad)
        hits = _binned_cells(model, x0 - gx0, y0 - gy0, (gy1 - gy0 + 1) // 2, (gx1 - gx0 + 1) // 2)
        near = np.empty(hits.shape, np.float32)
        for k in range(ORIENTATIONS):
            if hits[k].all():
                near[k] = self.tau
            else:
                near[k] = 2.0 * cv2.distanceTransform(hits[k], cv2.DIST_L2, 3)
        reverse = _reverse_cost(self.rows // 2, self.cols // 2, self.photo_bins, near, gx0 // 2, gy0 // 2,
                                float(self.tau)) / self.tau
        return forward, float((reverse + self.outside * self.clutter) / (self.rows.size + self.outside))

    def __call__(self, frame: Frame) -> float:
        forward, reverse = self.parts(frame)
        return forward + reverse
