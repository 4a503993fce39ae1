"""OpenCV pinhole camera: a mesh vertex X (mesh units) lands at pixel ``u ~ K (R X + t)``.

Pixel convention (method.md §1): x right, y down, the camera looks along +z, the centre of the
top-left pixel is (0, 0), so the image centre is ((W - 1) / 2, (H - 1) / 2).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from vehicle_pose.errors import CameraError

__all__ = ["Camera", "MAX_IMAGE_SIDE", "MAX_MAGNITUDE", "look_at_camera", "to_pixels"]

FloatArray = npt.NDArray[np.float64]

MAX_IMAGE_SIDE = 100_000
"""The largest image side a camera read from JSON may have (pixels)."""
MAX_MAGNITUDE = 1e9
"""The largest absolute entry of K (pixels) or t (mesh units) a camera read from JSON may have."""


def to_pixels(points: FloatArray, K: FloatArray) -> FloatArray:
    """Camera-frame points (N, 3) to pixels (N, 2) through the intrinsics ``K``; points behind
    the camera give nan."""
    uvw = points @ K.T
    with np.errstate(divide="ignore", invalid="ignore"):
        uv: FloatArray = uvw[:, :2] / uvw[:, 2:3]
    uv[points[:, 2] <= 0] = np.nan
    return uv


@dataclass(frozen=True)
class Camera:
    """A pinhole camera and the image it sees.

    Attributes
    ----------
    K : (3, 3) float64
        Intrinsics in pixels.
    R : (3, 3) float64
        Rotation, mesh (model) frame to camera frame, OpenCV axes.
    t : (3,) float64
        Translation, mesh units, camera frame.
    width, height : int
        Image size in pixels.
    """

    K: FloatArray
    R: FloatArray
    t: FloatArray
    width: int
    height: int

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64)
        R = np.asarray(self.R, dtype=np.float64)
        t = np.asarray(self.t, dtype=np.float64).reshape(-1)
        if K.shape != (3, 3) or R.shape != (3, 3) or t.shape != (3,):
            raise CameraError(f"camera needs K 3x3, R 3x3, t 3; got {K.shape}, {R.shape}, {t.shape}")
        # Checked on Python floats: a camera is built for every loss evaluation.
        k, r, tt = K.tolist(), R.tolist(), t.tolist()
        if not all(math.isfinite(v) for row in k + r + [tt] for v in row):
            raise CameraError("camera holds non-finite numbers")
        if (k[0][0] <= 0 or k[1][1] <= 0 or abs(k[2][2] - 1.0) > 1e-9 or k[1][0] != 0 or k[2][0] != 0
                or k[2][1] != 0):
            raise CameraError("K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")
        gram = max(abs(sum(a * b for a, b in zip(r[i], r[j], strict=True)) - (i == j))
                   for i in range(3) for j in range(i, 3))
        det = (r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1]) - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
               + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0]))
        if gram > 1e-6 or det < 0:
            raise CameraError("R is not a rotation matrix")
        if int(self.width) < 1 or int(self.height) < 1:
            raise CameraError(f"image size {self.width}x{self.height} is not positive")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @property
    def focal(self) -> float:
        """Mean focal length in pixels."""
        return float(0.5 * (self.K[0, 0] + self.K[1, 1]))

    @property
    def centre(self) -> FloatArray:
        """Principal point (cx, cy) in pixels."""
        return self.K[:2, 2].copy()

    def to_camera(self, points: npt.ArrayLike) -> FloatArray:
        """Mesh-frame points (N, 3) to camera-frame points (N, 3)."""
        return np.asarray(points, dtype=np.float64) @ self.R.T + self.t

    def project(self, points: npt.ArrayLike) -> FloatArray:
        """Mesh-frame points (N, 3) to pixels (N, 2); points behind the camera give nan."""
        return to_pixels(self.to_camera(points), self.K)

    def scaled(self, width: int, height: int) -> Camera:
        """The same camera for the photo resized to ``width`` x ``height`` (pixel centres kept)."""
        sx = width / self.width
        sy = height / self.height
        S = np.array([[sx, 0.0, 0.5 * (sx - 1.0)], [0.0, sy, 0.5 * (sy - 1.0)], [0.0, 0.0, 1.0]])
        return Camera(S @ self.K, self.R, self.t, width, height)

    def for_photo(self, width: int, height: int, *, tolerance: float = 0.01) -> Camera:
        """:meth:`scaled` to a photo of ``width`` x ``height``; CameraError when the photo's
        aspect ratio differs from the camera's by more than ``tolerance`` (a camera for another
        picture, or for the photo turned by its EXIF orientation, would be stretched)."""
        if (width, height) == (self.width, self.height):
            return self
        mine, theirs = self.width / self.height, width / height
        if abs(mine / theirs - 1.0) > tolerance:
            raise CameraError(
                f"the camera is for a {self.width}x{self.height} image and the photo is {width}x{height}: "
                f"another aspect ratio ({mine:.3f} against {theirs:.3f}), so it is not a camera of this photo"
            )
        return self.scaled(width, height)

    def cropped(self, x0: int, y0: int, width: int, height: int) -> Camera:
        """The same camera for the ``width`` x ``height`` window whose top-left pixel is (x0, y0)
        of this image; negative offsets place this image inside a larger one (the inverse)."""
        K = self.K.copy()
        K[0, 2] -= x0
        K[1, 2] -= y0
        return Camera(K, self.R, self.t, width, height)

    def to_dict(self) -> dict[str, Any]:
        return {
            "K": self.K.tolist(),
            "R": self.R.tolist(),
            "t": self.t.tolist(),
            "width": self.width,
            "height": self.height,
        }

    @classmethod
    def from_dict(cls, data: Any) -> Camera:
        """Build a camera from ``{"K", "R", "t", "width", "height"}``; CameraError if malformed,
        if the image is larger than :data:`MAX_IMAGE_SIDE` or a number of K or t beyond
        :data:`MAX_MAGNITUDE`."""
        if not isinstance(data, dict):
            raise CameraError("camera JSON must be an object with K, R, t, width, height")
        missing = [k for k in ("K", "R", "t", "width", "height") if k not in data]
        if missing:
            raise CameraError(f"camera JSON lacks {', '.join(missing)}")
        try:
            K = np.array(data["K"], dtype=np.float64)
            R = np.array(data["R"], dtype=np.float64)
            t = np.array(data["t"], dtype=np.float64).reshape(-1)
            width, height = int(data["width"]), int(data["height"])
        except (TypeError, ValueError, OverflowError) as exc:
            raise CameraError(f"camera JSON has a non-numeric or out-of-range entry: {exc}") from None
        if not (0 < width <= MAX_IMAGE_SIDE and 0 < height <= MAX_IMAGE_SIDE):
            raise CameraError(f"image size {width}x{height} is outside 1-{MAX_IMAGE_SIDE} pixels")
        if K.size and t.size and max(float(np.abs(K).max()), float(np.abs(t).max())) > MAX_MAGNITUDE:
            # Finite but beyond what a projection can use (the renderer divides by these).
            raise CameraError(f"camera K or t holds a number beyond {MAX_MAGNITUDE:g}")
        return cls(K, R, t, width, height)

    @classmethod
    def from_json(cls, text: str | bytes, *, what: str = "camera JSON") -> Camera:
        """A camera from JSON text; CameraError saying what is wrong (``what`` names the text)."""
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise CameraError(f"{what} is not valid JSON: {exc.msg} at line {exc.lineno}") from None
        except RecursionError:  # 100 000 nested brackets
            raise CameraError(f"{what} is nested too deeply to be a camera") from None
        except ValueError as exc:  # a 5000-digit integer
            reason = str(exc).splitlines()[0][:200] if str(exc) else type(exc).__name__
            raise CameraError(f"{what} cannot be read as a camera: {reason}") from None
        return cls.from_dict(data)

    @classmethod
    def load(cls, path: str | Path) -> Camera:
        """Read a camera JSON file; CameraError if it cannot be read or parsed."""
        try:
            text = Path(path).read_text()
        except OSError as exc:
            raise CameraError(f"cannot read camera file {path}: {exc.strerror}") from None
        return cls.from_json(text, what=f"camera file {path}")


def look_at_camera(
    centre: npt.ArrayLike,
    forward: npt.ArrayLike,
    up: npt.ArrayLike,
    *,
    azimuth_deg: float,
    elevation_deg: float,
    distance: float,
    focal: float,
    width: int,
    height: int,
) -> Camera:
    """A camera looking at ``centre`` from a direction given relative to the vehicle.

    Azimuth 0 looks at the vehicle's front, 90 at its left side; elevation is above the ground.
    """
    f = np.asarray(forward, np.float64)
    u = np.asarray(up, np.float64)
    left = np.cross(u, f)
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    d = np.cos(el) * (np.cos(az) * f + np.sin(az) * left) + np.sin(el) * u
    z = -d
    y = -(u - (u @ z) * z)
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    R = np.stack([x, y, z])
    eye = np.asarray(centre, np.float64) + distance * d
    K = np.array([[focal, 0.0, (width - 1) / 2.0], [0.0, focal, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
    return Camera(K, R, -R @ eye, width, height)

