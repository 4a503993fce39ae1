"""Vehicle pose registration: find a vehicle model's camera pose in one photo.

The engine is a pure library (no web, queue or database): render the model's normals with
OpenGL (headless EGL), score them against the photo with an illumination-invariant loss, remove
the background with GrabCut, and minimise with the downhill simplex (see ``docs/``).
"""

from typing import TYPE_CHECKING, Any

# Names are imported from their modules on first use (PEP 562), so that a command that needs
# only the model library does not pay for the renderer, the optimisers and trimesh.
_WHERE = {
    "Camera": "camera",
    "CameraError": "errors",
    "EmptyMeshError": "errors",
    "ModelError": "errors",
    "PhotoError": "errors",
    "PhotoTooLargeError": "errors",
    "PoseError": "errors",
    "RenderError": "errors",
    "UnknownModelError": "errors",
    "VehiclePoseError": "errors",
    "ModelLibrary": "library",
    "VehicleModel": "library",
    "model_from_mesh": "library",
    "InvariantLoss": "loss",
    "PhotoTarget": "loss",
    "invariant_loss": "loss",
    "Mesh": "mesh",
    "load_mesh": "mesh",
    "decode_photo": "photo",
    "load_photo": "photo",
    "RegistrationOptions": "options",
    "RegistrationResult": "pipeline",
    "register": "pipeline",
    "ModelStore": "store",
    "Theta": "pose",
    "camera_to_theta": "pose",
    "theta_to_camera": "pose",
}

if TYPE_CHECKING:
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
    from .options import RegistrationOptions
    from .photo import decode_photo, load_photo
    from .pipeline import RegistrationResult, register
    from .pose import Theta, camera_to_theta, theta_to_camera
    from .store import ModelStore


def __getattr__(name: str) -> Any:
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module 'vehicle_pose' has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_WHERE])


__version__ = "0.1.0"

__all__ = [
    "Camera",
    "CameraError",
    "EmptyMeshError",
    "InvariantLoss",
    "Mesh",
    "ModelError",
    "ModelLibrary",
    "ModelStore",
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
