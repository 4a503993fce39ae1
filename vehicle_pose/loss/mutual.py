"""Material-colour mutual information: how much the rendered model's parts tell about the
photo's colours, over the whole frame (``docs/decisions/0014-photo-search.md``).

The invariant loss asks whether some lighting of the model's normals explains the photo's
pixels; on a real photo the paint and the glass mirror their surroundings and no lighting
does. What does hold on a real photo is weaker and coarser: the pixels of one part of the car
(the glass, the tyres, the lights, the body) share colours among themselves, and differ from the
background's. Region-based trackers build on this (PWP3D, Prisacariu and Reid 2012: the
foreground and background colour posteriors that a pose's silhouette induces); with more than
two regions and no colour model learnt beforehand, the natural score is the mutual information
between the label each pixel gets from the rendered pose (background, or the material kind of
the part it shows: body, glass, tyre, wheel, light, other; optionally split by the part's ambient
shade) and the photo's colour class at that pixel:

    I(M; C) = sum_{m,c} p(m, c) log(p(m, c) / (p(m) p(c)))

It is high when the pose's parts split the photo into regions of distinct colours, whatever
those colours are (a white car on a white floor scores by its dark glass and tyres), and about
zero for a pose whose silhouette covers the whole frame or lies across the car. It is coarse
(a few degrees either way hardly change it) but holds at large errors where the chamfer of the
photo's edges does not: it tells front from back and the car from its mirror image on the
floor, which is what it is used for (ranking whole-turn hypotheses, never polishing).

The photo's colour classes come from k-means in CIE Lab, started from the same seed every
time so that one photo always gets the same classes.
"""

from __future__ import annotations

import cv2
import numpy as np
import numpy.typing as npt

from vehicle_pose.geometry.camera import Camera
from vehicle_pose.model.mesh import Mesh
from vehicle_pose.photo import resized
from vehicle_pose.render.renderer import Frame, Renderer

__all__ = ["colour_classes", "material_codes", "mutual_information", "MaterialInformation"]

_SEED = 1234  # k-means's seed: the same photo always gets the same classes


def colour_classes(rgb: npt.NDArray[np.uint8], clusters: int) -> npt.NDArray[np.int32]:
    """Each pixel's colour class (0 .. ``clusters`` - 1): k-means of the CIE Lab colours,
    k-means++ from a fixed seed (deterministic for one photo)."""
    lab = cv2.cvtColor(rgb, cv2.COLOR_RGB2LAB).reshape(-1, 3).astype(np.float32)
    k = int(min(clusters, len(np.unique(lab, axis=0))))
    if k < 2:
        return np.zeros(rgb.shape[:2], np.int32)
    cv2.setRNGSeed(_SEED)
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.5)
    _, labels, _ = cv2.kmeans(lab, k, None, criteria, 2, cv2.KMEANS_PP_CENTERS)
    out: npt.NDArray[np.int32] = np.asarray(labels, np.int32).reshape(rgb.shape[:2])
    return out


def material_codes(frame: Frame, shades: int = 1) -> npt.NDArray[np.int32]:
    """The frame's part code at every pixel of the image: 0 for background, else 1 + the
    material kind times ``shades`` + the level of its ambient shade ``k_a`` in ``shades`` levels
    (with more than one, a painted body and its black trim are different parts)."""
    if frame.pixel_count == 0:
        return np.zeros((frame.height, frame.width), np.int32)
    kind = frame.labels.astype(np.int32) - 1
    shade = np.clip(np.rint(frame.attrs[..., 0] * (shades - 1)), 0, shades - 1).astype(np.int32)
    return frame.full(np.where(frame.labels > 0, 1 + kind * shades + shade, 0).astype(np.int32))


def mutual_information(a: npt.NDArray[np.int32], b: npt.NDArray[np.int32], nb: int) -> float:
    """The mutual information (nats) of two label images, ``b`` in 0 .. ``nb`` - 1."""
    joint = np.bincount((a.ravel() * nb + b.ravel()), minlength=(int(a.max()) + 1) * nb).astype(np.float64)
    p = joint.reshape(-1, nb) / max(joint.sum(), 1.0)
    pa, pb = p.sum(1, keepdims=True), p.sum(0, keepdims=True)
    nz = p > 0
    return float((p[nz] * np.log(p[nz] / (pa @ pb)[nz])).sum())


class MaterialInformation:
    """The mutual information of ``mesh``'s parts, rendered by a camera, with the colour classes
    of ``rgb`` reduced to ``size`` pixels (its longer side); called with a camera for ``rgb``'s
    size. ``entropy`` is the photo's colour entropy, the score's upper bound; ``shades`` as in
    :func:`material_codes`."""

    def __init__(self, rgb: npt.NDArray[np.uint8], mesh: Mesh, renderer: Renderer, *, size: int = 320,
                 clusters: int = 12, shades: int = 1) -> None:
        H, W = rgb.shape[:2]
        s = min(1.0, size / max(W, H))
        self.width, self.height = max(8, round(W * s)), max(8, round(H * s))
        self.classes = colour_classes(resized(rgb, self.width, self.height), clusters)
        self.n_classes = int(self.classes.max()) + 1
        counts = np.bincount(self.classes.ravel()).astype(np.float64)
        p = counts[counts > 0] / counts.sum()
        self.entropy = float(-(p * np.log(p)).sum())
        self.mesh, self.renderer, self.shades = mesh, renderer, shades

    def __call__(self, camera: Camera) -> float:
        frame = self.renderer.render(self.mesh, camera.scaled(self.width, self.height))
        return mutual_information(material_codes(frame, self.shades), self.classes, self.n_classes)
