"""Background removal with GrabCut seeded by the start pose (method.md §5, step 2).

Outside the projected silhouette grown by a margin is background; inside it shrunk by the margin
is probable foreground; the ring between is probable background outside the silhouette and
probable foreground inside it. GrabCut runs on a crop around the grown silhouette, reduced to a
bounded size, so its cost does not grow with the photo.
"""

from __future__ import annotations

import cv2
import numpy as np
import numpy.typing as npt

from vehicle_pose.clock import timed

__all__ = ["grabcut_foreground", "disk"]


def disk(radius: int) -> npt.NDArray[np.uint8]:
    """A disk-shaped structuring element of the given radius (pixels) for OpenCV morphology."""
    kernel: npt.NDArray[np.uint8] = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
    return kernel


@timed("grabcut")
def grabcut_foreground(
    rgb: npt.NDArray[np.uint8],
    silhouette: npt.NDArray[np.bool_],
    *,
    margin: float = 0.06,
    max_size: int = 320,
    iterations: int = 4,
    sure_core: bool = False,
    region: npt.NDArray[np.bool_] | None = None,
) -> npt.NDArray[np.bool_]:
    """The vehicle's pixels, seeded by the silhouette of a start pose.

    Parameters
    ----------
    rgb : (H, W, 3) uint8
        The photo.
    silhouette : (H, W) bool
        The model's projection at the start pose.
    margin : float, keyword-only
        Grow/shrink margin as a fraction of the silhouette box's diagonal.
    max_size : int, keyword-only
        GrabCut runs on the crop reduced to at most this many pixels on its longer side.
    iterations : int, keyword-only
    sure_core : bool, keyword-only
        Mark the shrunk silhouette as certain foreground (for a pose already close).
    region : (H, W) bool, optional, keyword-only
        Pixels that may show the vehicle besides the grown silhouette (e.g. the client's box):
        they are probable background rather than certain background, so GrabCut can claim
        the parts of the vehicle that a rough start pose misses.

    Returns
    -------
    (H, W) bool
        Foreground; the grown silhouette when GrabCut keeps too little of it.
    """
    H, W = silhouette.shape
    ys, xs = np.nonzero(silhouette)
    if ys.size == 0:
        return np.ones((H, W), bool)
    diag = float(np.hypot(xs.max() - xs.min(), ys.max() - ys.min()))
    m = max(2, int(round(margin * diag)))
    pad = 2 * m
    if region is not None and region.any():
        ry, rx = np.nonzero(region)
        ys = np.concatenate([ys, ry[[0, -1]]])
        xs = np.concatenate([xs, [rx.min(), rx.max()]])
    x0, x1 = max(xs.min() - pad, 0), min(xs.max() + pad + 1, W)
    y0, y1 = max(ys.min() - pad, 0), min(ys.max() + pad + 1, H)
    crop_sil = silhouette[y0:y1, x0:x1].astype(np.uint8)
    crop_region = None if region is None else region[y0:y1, x0:x1].astype(np.uint8)
    crop = rgb[y0:y1, x0:x1]
    scale = min(1.0, max_size / max(crop.shape[:2]))
    if scale < 1.0:
        size = (max(1, round(crop.shape[1] * scale)), max(1, round(crop.shape[0] * scale)))
        crop = cv2.resize(crop, size, interpolation=cv2.INTER_AREA)
        crop_sil = cv2.resize(crop_sil, size, interpolation=cv2.INTER_NEAREST)
        if crop_region is not None:
            crop_region = cv2.resize(crop_region, size, interpolation=cv2.INTER_NEAREST)
    ms = max(1, int(round(m * scale)))
    grown = cv2.dilate(crop_sil, disk(ms)).astype(bool)
    if crop_region is not None:
        grown |= crop_region.astype(bool)
    shrunk = cv2.erode(crop_sil, disk(ms)).astype(bool)
    inside = crop_sil.astype(bool)
    mask = np.full(crop_sil.shape, cv2.GC_BGD, np.uint8)
    mask[grown] = cv2.GC_PR_BGD
    mask[inside] = cv2.GC_PR_FGD
    mask[shrunk] = cv2.GC_FGD if sure_core else cv2.GC_PR_FGD
    fallback = np.zeros((H, W), bool)
    fallback[y0:y1, x0:x1] = cv2.resize(grown.astype(np.uint8), (x1 - x0, y1 - y0), interpolation=cv2.INTER_NEAREST) > 0
    if not (mask == cv2.GC_BGD).any() or inside.sum() < 16:
        return fallback
    bgd = np.zeros((1, 65), np.float64)
    fgd = np.zeros((1, 65), np.float64)
    bgr = cv2.cvtColor(np.ascontiguousarray(crop), cv2.COLOR_RGB2BGR)
    cv2.setRNGSeed(0)
    cv2.grabCut(bgr, mask, None, bgd, fgd, iterations, cv2.GC_INIT_WITH_MASK)
    fg = ((mask == cv2.GC_FGD) | (mask == cv2.GC_PR_FGD)).astype(np.uint8)
    if fg.sum() < 0.3 * inside.sum():
        return fallback
    fg = cv2.morphologyEx(fg, cv2.MORPH_CLOSE, disk(max(1, ms // 2)))
    out = np.zeros((H, W), bool)
    out[y0:y1, x0:x1] = cv2.resize(fg, (x1 - x0, y1 - y0), interpolation=cv2.INTER_NEAREST) > 0
    return out
