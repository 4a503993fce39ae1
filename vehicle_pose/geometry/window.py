"""A window of the photo around the vehicle, reduced: where the coarse searches look.

The start-pose searches run on reduced images, and a vehicle that fills a small part of the
photo would cover only a few hundred of their pixels. A :class:`Window` is the vehicle's box
grown by a margin, cut from the working image and reduced to a bounded size (never enlarged),
so the searches see the vehicle at about the same resolution whatever its size in the photo.
Cameras, images and masks move between the full image and the window.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from vehicle_pose.geometry.camera import Camera
from vehicle_pose.photo import resized

__all__ = ["Window"]


@dataclass(frozen=True)
class Window:
    """Pixels ``x0 <= x < x1``, ``y0 <= y < y1`` of a ``full_width`` x ``full_height`` image,
    reduced to ``width`` x ``height``."""

    x0: int
    y0: int
    x1: int
    y1: int
    full_width: int
    full_height: int
    width: int
    height: int

    @classmethod
    def around(
        cls,
        box: tuple[float, float, float, float] | None,
        full_width: int,
        full_height: int,
        *,
        size: int,
        margin: float | None,
    ) -> Window:
        """The box (X0, Y0, X1, Y1) grown on every side by ``margin`` times its longer side,
        within the image, reduced to at most ``size`` pixels on its longer side. With no box or
        no margin, the whole image."""
        if box is None or margin is None:
            x0, y0, x1, y1 = 0, 0, full_width, full_height
        else:
            g = margin * max(box[2] - box[0], box[3] - box[1])
            x0, y0 = max(0, int(np.floor(box[0] - g))), max(0, int(np.floor(box[1] - g)))
            x1 = min(full_width, int(np.ceil(box[2] + g)) + 1)
            y1 = min(full_height, int(np.ceil(box[3] + g)) + 1)
            if x1 - x0 < 8 or y1 - y0 < 8:
                x0, y0, x1, y1 = 0, 0, full_width, full_height
        s = min(1.0, size / max(x1 - x0, y1 - y0))
        return cls(x0, y0, x1, y1, full_width, full_height,
                   max(8, round((x1 - x0) * s)), max(8, round((y1 - y0) * s)))

    @property
    def crop_size(self) -> tuple[int, int]:
        return self.x1 - self.x0, self.y1 - self.y0

    def image(self, rgb: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
        """The window of a full-size image, reduced."""
        crop = rgb[self.y0 : self.y1, self.x0 : self.x1]
        if crop.shape[1] == self.width and crop.shape[0] == self.height:
            return crop
        return resized(np.ascontiguousarray(crop), self.width, self.height)

    def mask(self, mask: npt.NDArray[np.bool_]) -> npt.NDArray[np.bool_]:
        """The window of a full-size mask, reduced."""
        crop = mask[self.y0 : self.y1, self.x0 : self.x1].astype(np.uint8)
        out: npt.NDArray[np.bool_] = cv2.resize(crop, (self.width, self.height), interpolation=cv2.INTER_NEAREST) > 0
        return out

    def full_mask(self, mask: npt.NDArray[np.bool_]) -> npt.NDArray[np.bool_]:
        """A window mask at the full image's size (False outside the window)."""
        out = np.zeros((self.full_height, self.full_width), bool)
        out[self.y0 : self.y1, self.x0 : self.x1] = cv2.resize(
            mask.astype(np.uint8), self.crop_size, interpolation=cv2.INTER_NEAREST) > 0
        return out

    def camera(self, camera: Camera) -> Camera:
        """A camera of the full image (at any size) as a camera of the window."""
        full = camera.scaled(self.full_width, self.full_height)
        return full.cropped(self.x0, self.y0, *self.crop_size).scaled(self.width, self.height)

    def full_camera(self, camera: Camera) -> Camera:
        """A camera of the window as a camera of the full image."""
        crop = camera.scaled(*self.crop_size)
        return crop.cropped(-self.x0, -self.y0, self.full_width, self.full_height)
