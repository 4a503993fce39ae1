"""The registration's segmentation of the working photo: GrabCut seeded by a pose.

The first mask is seeded by the start pose's silhouette; after each coarse level it is made
again, seeded by that level's pose (``docs/decisions/0004-resegmentation.md``).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from vehicle_pose.geometry.camera import Camera
from vehicle_pose.model.library import VehicleModel
from vehicle_pose.photo import resized_mask
from vehicle_pose.registration.options import Segmentation
from vehicle_pose.render.renderer import Renderer
from vehicle_pose.search.views import Box
from vehicle_pose.segment.grabcut import grabcut_foreground

__all__ = ["OUTLINE_FACES", "silhouette", "first_foreground", "resegment", "box_mask"]

OUTLINE_FACES = 16384
"""Faces of the level of detail whose silhouette seeds GrabCut and is checked against the region."""


def silhouette(model: VehicleModel, camera: Camera, renderer: Renderer) -> npt.NDArray[np.bool_]:
    """(H, W) bool: the pixels the model covers seen by ``camera``."""
    return renderer.render(model.lod(OUTLINE_FACES), camera).coverage


def box_mask(box: Box, width: int, height: int, margin: float) -> npt.NDArray[np.bool_]:
    """The box (x0, y0, x1, y1, pixels) grown by ``margin`` of its diagonal, as a (height, width) mask."""
    x0, y0, x1, y1 = box
    g = margin * float(np.hypot(x1 - x0, y1 - y0))
    mask = np.zeros((height, width), bool)
    mask[max(0, int(y0 - g)) : max(0, int(np.ceil(y1 + g)) + 1),
         max(0, int(x0 - g)) : max(0, int(np.ceil(x1 + g)) + 1)] = True
    return mask


def doubt_weights(
    foreground: npt.NDArray[np.bool_], region: npt.NDArray[np.bool_] | None, weight: float
) -> npt.NDArray[np.float64] | None:
    """Loss weights (H, W) at ``foreground``'s size: ``weight`` on the pixels of ``region`` (the
    client's grown box, at any size) that GrabCut left out, 1 elsewhere; None (unit weights)
    without a region or at weight 1.

    Within the box, background is GrabCut's guess, and on real photos a poor one: it drops the
    dark sills, tyres and shadow under a car and the glass that mirrors the sky. Beyond the box
    it is certain.
    """
    if region is None or weight >= 1.0:
        return None
    h, w = foreground.shape
    doubtful = resized_mask(region, w, h) & ~foreground
    if not doubtful.any():
        return None
    return np.where(doubtful, float(weight), 1.0)


def first_foreground(
    work: npt.NDArray[np.uint8],
    start_silhouette: npt.NDArray[np.bool_],
    options: Segmentation,
    region: npt.NDArray[np.bool_] | None,
) -> npt.NDArray[np.bool_]:
    """The vehicle's pixels (H, W) of the working photo, seeded by the start silhouette grown by
    ``grabcut_margin``; ``region`` (the client's grown box) may also be claimed. Every pixel
    when GrabCut is off."""
    if not options.grabcut:
        return np.ones(work.shape[:2], bool)
    return grabcut_foreground(work, start_silhouette, margin=options.grabcut_margin, region=region)


def resegment(
    work: npt.NDArray[np.uint8],
    model: VehicleModel,
    camera: Camera,
    options: Segmentation,
    renderer: Renderer,
    region: npt.NDArray[np.bool_] | None,
    size: int,
) -> npt.NDArray[np.bool_] | None:
    """GrabCut seeded by a pose already close (its shrunk silhouette certain foreground), run
    at ``size`` pixels (at least 320) on the longer side; None when the pose shows too little."""
    current = silhouette(model, camera, renderer)
    if current.sum() < 16:
        return None
    return grabcut_foreground(work, current, margin=options.resegment_margin, sure_core=True,
                              iterations=options.resegment_iterations, region=region, max_size=max(320, size))
