"""Vehicle pose registration: find a vehicle model's camera pose in one photo.

The engine is a pure library (no web, queue or database): render the model's normals with
OpenGL (headless EGL), score them against the photo with an illumination-invariant loss, remove
the background with GrabCut, and minimise with the downhill simplex (see ``docs/``).
"""

from .camera import Camera
from .errors import (
    CameraError,
    EmptyMeshError,
    ModelError,
    PhotoError,
    PhotoTooLargeError,
    PoseError,
    RenderError,
    UnknownModelError,
    VehiclePoseError,
)
from .library import ModelLibrary, VehicleModel, model_from_mesh
from .loss import InvariantLoss, PhotoTarget, invariant_loss
from .mesh import Mesh, load_mesh
from .photo import decode_photo, load_photo
from .pipeline import RegistrationOptions, RegistrationResult, register
from .pose import Theta, camera_to_theta, theta_to_camera

__version__ = "0.1.0"

__all__ = [
    "Camera",
    "CameraError",
    "EmptyMeshError",
    "InvariantLoss",
    "Mesh",
    "ModelError",
    "ModelLibrary",
    "PhotoError",
    "PhotoTooLargeError",
    "PhotoTarget",
    "PoseError",
    "RegistrationOptions",
    "RegistrationResult",
    "RenderError",
    "Theta",
    "UnknownModelError",
    "VehicleModel",
    "VehiclePoseError",
    "camera_to_theta",
    "decode_photo",
    "invariant_loss",
    "load_mesh",
    "load_photo",
    "model_from_mesh",
    "register",
    "theta_to_camera",
]
