"""Typed errors raised by the engine; each carries a one-line reason a caller can show."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from vehicle_pose.geometry.camera import Camera


class VehiclePoseError(Exception):
    """Base class of every error the engine raises on bad input."""

    code = "vehicle-pose-error"


class PhotoError(VehiclePoseError):
    """The photo cannot be read or is not a usable image."""

    code = "unreadable-photo"


class PhotoTooLargeError(PhotoError):
    """The photo has more pixels than allowed (a decompression bomb, or simply too large)."""

    code = "photo-too-large"


class BlankPhotoError(PhotoError):
    """The photo is one flat colour: there is nothing to register on."""

    code = "blank-photo"


class ModelError(VehiclePoseError):
    """The vehicle model cannot be found, loaded or used."""

    code = "invalid-model"


class UnknownModelError(ModelError):
    """No model with this id exists in the library."""

    code = "unknown-model"


class EmptyMeshError(ModelError):
    """The mesh file holds no triangles."""

    code = "empty-mesh"


class CameraError(VehiclePoseError):
    """A camera (start pose) is malformed or inconsistent."""

    code = "invalid-camera"


class PoseError(VehiclePoseError):
    """A pose cannot be used: the model is behind the camera or off-screen."""

    code = "invalid-pose"


class RenderError(VehiclePoseError):
    """The OpenGL context could not be created or rendering failed."""

    code = "render-failed"


class OutOfTime(VehiclePoseError):
    """The registration reached its deadline and stopped; ``camera`` is the best pose it had
    found by then (for the photo as given; None before the first stage ended) and ``stage``
    the stage that found it."""

    code = "timeout"

    def __init__(self, message: str, camera: Camera | None = None, stage: str | None = None) -> None:
        super().__init__(message)
        self.camera = camera
        self.stage = stage
