"""The paper's vehicle pose parameters theta and their exact camera (method.md §3).

theta = (mu_x, mu_y, delta_x, delta_y, psi_x, psi_y, f): mu is the image position of the visible
rear wheel centre, delta the image vector to the front wheel centre on the same side, psi the unit
axle direction in camera coordinates pointing out of the visible side (psi_z < 0), f the focal
length in pixels. The optimiser works on ``(mu_x/W, mu_y/H, delta_x/W, delta_y/H, psi_x, psi_y,
10 W / f)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt

from vehicle_pose.errors import PoseError
from vehicle_pose.geometry.camera import Camera

__all__ = [
    "Side",
    "SideGeometry",
    "Theta",
    "theta_to_camera",
    "camera_to_theta",
    "visible_side",
]

Side = Literal["left", "right"]
FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class SideGeometry:
    """Wheel centres and outward axle of one side of the vehicle, mesh frame and units.

    Attributes
    ----------
    rear, front : (3,) float64
        Rear and front wheel centres W_r, W_f on this side.
    axle : (3,) float64
        Unit axle direction pointing out of this side, orthogonal to ``front - rear``.
    """

    rear: FloatArray
    front: FloatArray
    axle: FloatArray

    @property
    def wheelbase(self) -> float:
        return float(np.linalg.norm(self.front - self.rear))

    @property
    def forward(self) -> FloatArray:
        """Unit vector b from the rear to the front wheel centre."""
        return (self.front - self.rear) / self.wheelbase

    @property
    def model_frame(self) -> FloatArray:
        """(3, 3) columns (a, b, a x b): axle, forward and their cross product."""
        a, b = self.axle, self.forward
        return np.column_stack([a, b, np.cross(a, b)])


@dataclass(frozen=True)
class Theta:
    """Pose parameters; mu, delta and f in pixels, psi a unit vector (camera frame)."""

    mu: FloatArray
    delta: FloatArray
    psi: FloatArray
    f: float
    side: Side

    def vector(self) -> FloatArray:
        """The paper's 7 parameters (mu_x, mu_y, delta_x, delta_y, psi_x, psi_y, f)."""
        return np.array([*self.mu, *self.delta, self.psi[0], self.psi[1], self.f])

    def normalized(self, width: int, height: int) -> FloatArray:
        """The optimiser's vector (mu_x/W, mu_y/H, delta_x/W, delta_y/H, psi_x, psi_y, 10W/f)."""
        return np.array(
            [
                self.mu[0] / width,
                self.mu[1] / height,
                self.delta[0] / width,
                self.delta[1] / height,
                self.psi[0],
                self.psi[1],
                10.0 * width / self.f,
            ]
        )

    @classmethod
    def from_normalized(cls, x: npt.ArrayLike, width: int, height: int, side: Side) -> Theta:
        """Inverse of :meth:`normalized`; PoseError when psi or f leave their domain."""
        v = np.asarray(x, dtype=np.float64)
        psi_xy = v[4:6]
        r2 = float(psi_xy @ psi_xy)
        if not r2 < 1.0 or v[6] <= 0.0:
            raise PoseError("theta out of domain: |psi_xy| >= 1 or f <= 0")
        psi = np.array([psi_xy[0], psi_xy[1], -np.sqrt(1.0 - r2)])
        return cls(
            np.array([v[0] * width, v[1] * height]),
            np.array([v[2] * width, v[3] * height]),
            psi,
            float(10.0 * width / v[6]),
            side,
        )

    def to_dict(self) -> dict[str, object]:
        return {
            "mu": self.mu.tolist(),
            "delta": self.delta.tolist(),
            "psi": self.psi.tolist(),
            "f": self.f,
            "side": self.side,
        }


def _orthonormal_pair(psi: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Two unit vectors e1, e2 with (e1, e2, psi) orthonormal."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(psi[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(psi, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(psi, e1)


def _cross2(a: FloatArray, b: FloatArray) -> float:
    return float(a[0] * b[1] - a[1] * b[0])


def theta_to_camera(theta: Theta, geometry: SideGeometry, width: int, height: int) -> Camera:
    """The exact camera (K, R, t) of theta for one side of the vehicle.

    K has focal length f and the image centre as principal point; R maps the side's axle a to
    psi and its forward direction b to the unit u orthogonal to psi for which both wheel centres
    project exactly onto mu and mu + delta.

    Raises
    ------
    PoseError
        theta is degenerate: zero delta, or no solution puts the vehicle in front of the camera.
    """
    f = float(theta.f)
    psi = np.asarray(theta.psi, dtype=np.float64)
    psi = psi / np.linalg.norm(psi)
    mu = np.asarray(theta.mu, dtype=np.float64)
    delta = np.asarray(theta.delta, dtype=np.float64)
    dd = float(delta @ delta)
    if not (f > 0.0 and np.isfinite(f)) or dd < 1e-12:
        raise PoseError("degenerate theta: f must be positive and delta non-zero")
    c = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
    p = (mu - c) / f
    q = (mu + delta - c) / f
    e1, e2 = _orthonormal_pair(psi)
    w1 = q * e1[2] - e1[:2]
    w2 = q * e2[2] - e2[:2]
    # cross2(cos(al) w1 + sin(al) w2, delta) = 0 has the solutions al0 and al0 + pi.
    al = np.arctan2(-_cross2(w1, delta), _cross2(w2, delta))
    u = np.cos(al) * e1 + np.sin(al) * e2
    w = np.cos(al) * w1 + np.sin(al) * w2
    if float(w @ delta) > 0.0:
        u, w = -u, -w
    wd = float(w @ delta)
    if wd >= 0.0:
        raise PoseError("degenerate theta: no pose puts both wheels in front of the camera")
    B = geometry.wheelbase
    z_r = -f * B * wd / dd
    x_r = z_r * np.array([p[0], p[1], 1.0])
    if z_r + B * u[2] <= 0.0:
        raise PoseError("degenerate theta: the front wheel lies behind the camera")
    R = np.column_stack([psi, u, np.cross(psi, u)]) @ geometry.model_frame.T
    t = x_r - R @ geometry.rear
    K = np.array([[f, 0.0, c[0]], [0.0, f, c[1]], [0.0, 0.0, 1.0]])
    return Camera(K, R, t, width, height)


def visible_side(camera: Camera, left: SideGeometry) -> Side:
    """The side whose outward axle points towards the camera (psi_z < 0)."""
    return "left" if float((camera.R @ left.axle)[2]) < 0.0 else "right"


def camera_to_theta(camera: Camera, geometry: SideGeometry, side: Side) -> Theta:
    """theta of a camera for the given side (``geometry`` must describe that side).

    The principal point of a camera whose K does not have it at the image centre, or whose
    pixels are not square, cannot be represented; f is then the mean focal length.
    """
    psi = camera.R @ geometry.axle
    uv = camera.project(np.stack([geometry.rear, geometry.front]))
    if not np.all(np.isfinite(uv)):
        raise PoseError("a wheel centre lies behind the camera")
    if psi[2] >= 0.0:
        raise PoseError(f"the {side} side faces away from the camera")
    return Theta(uv[0], uv[1] - uv[0], psi, camera.focal, side)
