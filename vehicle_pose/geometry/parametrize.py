"""Search coordinates for the optimiser: the paper's theta, or a local view parametrisation.

``theta`` (default, method.md §3): ``(mu_x/W, mu_y/H, delta_x/W, delta_y/H, psi_x, psi_y, 10W/f)``
for one visible side. It degenerates for nearly frontal or rear views, where the two wheels of a
side overlap in the image (delta -> 0) and psi nears the edge of its domain.

``view``: a perturbation of a reference camera about the model's centre: rotation vector (3,
radians), image position of the centre (2, fractions of W and H), log apparent scale and log
focal length (the depth follows f, so changing f alone changes only the perspective). It is
regular for every view.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Protocol

import cv2
import numpy as np
import numpy.typing as npt

from vehicle_pose.geometry.camera import Camera
from vehicle_pose.geometry.pose import Side, SideGeometry, Theta, camera_to_theta, theta_to_camera
from vehicle_pose.registry import PARAMETRIZATIONS

__all__ = ["Parametrization", "SearchFrame", "ThetaParams", "ViewParams", "make_parametrization"]

FloatArray = npt.NDArray[np.float64]


class Parametrization(Protocol):
    def start(self) -> FloatArray:
        """Coordinates (7,) of the reference camera."""
        ...

    def steps(self) -> FloatArray:
        """Initial simplex steps (7,) of the coarsest level."""
        ...

    def camera(self, x: FloatArray) -> Camera:
        """The camera of coordinates x; PoseError when x is out of the domain."""
        ...


@dataclass(frozen=True)
class SearchFrame:
    """What search coordinates know of the model.

    ``centre`` (3,) and ``radius`` are its bounding sphere (mesh units), ``geometry`` the wheel
    geometry of the visible ``side``, ``pivot`` where a dolly zoom keeps the image size, in
    bounding-sphere radii in front of the centre (:class:`ViewParams`); ``focal_band`` the
    focal lengths (image widths, low and high) the search may reach, None for any.
    """

    centre: FloatArray
    radius: float
    geometry: SideGeometry
    side: Side
    pivot: float = 0.0
    focal_band: tuple[float, float] | None = None


@dataclass(frozen=True)
class ThetaParams:
    """The paper's normalised theta for one side, at one image size."""

    reference: Camera
    geometry: SideGeometry
    side: Side
    focal_band: tuple[float, float] | None = None

    def start(self) -> FloatArray:
        c = self.reference
        return camera_to_theta(c, self.geometry, self.side).normalized(c.width, c.height)

    def steps(self) -> FloatArray:
        x6 = self.start()[6]
        return np.array([0.03, 0.03, 0.03, 0.03, 0.08, 0.08, 0.25 * max(x6, 0.5)])

    def camera(self, x: FloatArray) -> Camera:
        w, h = self.reference.width, self.reference.height
        if self.focal_band is not None:
            # The coordinate is 10 W / f: the band of f held by clipping it.
            x = np.array(x, np.float64)
            x[6] = np.clip(x[6], 10.0 / self.focal_band[1], 10.0 / self.focal_band[0])
        return theta_to_camera(Theta.from_normalized(x, w, h, self.side), self.geometry, w, h)


@dataclass(frozen=True)
class ViewParams:
    """Rotation vector, centre position, log scale and log focal length about a reference.

    ``x = (r, u, v, s, g)``: the camera turns by the rotation vector ``r`` about the model's
    centre, the centre's image moves by ``(u, v)`` image sizes, ``s`` is the log of the image
    scale and ``g`` the log of the focal length. The scale is measured at the depth ``pivot``
    (mesh units) in front of the centre, at most half the centre's depth: a change of focal
    length alone is a dolly zoom that keeps the size of what lies there, and with the pivot
    near the visible outline (rather than at the centre) focal length and scale are nearly
    independent coordinates for the simplex. With a ``focal_band`` (image widths, low and
    high) the focal length is held inside it: ``g`` is clipped, and beyond the band the
    coordinate changes nothing (a flat prior, as a lens known within a tolerance gives).
    """

    reference: Camera
    centre: FloatArray
    pivot: float = 0.0
    focal_band: tuple[float, float] | None = None

    def start(self) -> FloatArray:
        return np.zeros(7)

    def steps(self) -> FloatArray:
        return np.array([0.08, 0.08, 0.08, 0.03, 0.03, 0.05, 0.3])

    @cached_property
    def _centre_view(self) -> tuple[float, FloatArray]:
        """Depth (mesh units) and pixel (2,) of the model centre in the reference camera."""
        ref = self.reference
        return float(ref.to_camera(self.centre[None])[0, 2]), ref.project(self.centre[None])[0]

    def camera(self, x: FloatArray) -> Camera:
        ref = self.reference
        f0 = ref.focal
        depth0, pix0 = self._centre_view
        g = x[6]
        if self.focal_band is not None:
            g = np.clip(g, np.log(self.focal_band[0] * ref.width / f0), np.log(self.focal_band[1] * ref.width / f0))
        f = f0 * np.exp(g)
        ahead = min(self.pivot, 0.5 * depth0)
        z = ahead + (depth0 - ahead) * np.exp(g - x[5])
        u = pix0[0] + x[3] * ref.width
        v = pix0[1] + x[4] * ref.height
        K = ref.K.copy()
        K[0, 0] *= f / f0
        K[1, 1] *= f / f0
        centre_cam = z * np.array([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], 1.0])
        # OpenCV's Rodrigues: the same matrix as SciPy's Rotation.from_rotvec, 10x faster.
        R = cv2.Rodrigues(np.asarray(x[:3], dtype=np.float64))[0] @ ref.R
        return Camera(K, R, centre_cam - R @ self.centre, ref.width, ref.height)

    @classmethod
    def about(cls, reference: Camera, frame: SearchFrame) -> ViewParams:
        """View coordinates about ``reference``, pivoted and banded as ``frame`` says."""
        return cls(reference, frame.centre, frame.pivot * frame.radius, frame.focal_band)

    def dolly_zoom(self, factor: float) -> Camera:
        """The reference with its focal length times ``factor`` and the depth following: the
        same centre and orientation in the image and the same size at the pivot, another
        perspective."""
        x = np.zeros(7)
        x[6] = np.log(factor)
        return self.camera(x)


@PARAMETRIZATIONS.register("view")
def _view(reference: Camera, frame: SearchFrame) -> ViewParams:
    return ViewParams.about(reference, frame)


@PARAMETRIZATIONS.register("theta")
def _theta(reference: Camera, frame: SearchFrame) -> ThetaParams:
    return ThetaParams(reference, frame.geometry, frame.side, frame.focal_band)


def make_parametrization(name: str, reference: Camera, frame: SearchFrame) -> Parametrization:
    """The coordinates called ``name`` about ``reference``; ValueError for an unknown name."""
    params: Parametrization = PARAMETRIZATIONS.get(name)(reference, frame)
    return params
