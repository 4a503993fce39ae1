"""Vehicle pose registration: find a vehicle model's camera pose in one photo.

The engine is a pure library (no web, queue or database): render the model's normals with
OpenGL (headless EGL), score them against the photo with an illumination-invariant loss, remove
the background with GrabCut, and minimise with the downhill simplex (see ``docs/``).
"""

from typing import TYPE_CHECKING, Any

# Names are imported from their modules on first use (PEP 562), so that a command that needs
# only the model library does not pay for the renderer, the optimisers and trimesh.
_WHERE = {
    "Camera": "geometry.camera",
    "CameraError": "errors",
    "EmptyMeshError": "errors",
    "ModelError": "errors",
    "PhotoError": "errors",
    "PhotoTooLargeError": "errors",
    "PoseError": "errors",
    "RenderError": "errors",
    "UnknownModelError": "errors",
    "VehiclePoseError": "errors",
    "ModelLibrary": "model.library",
    "VehicleModel": "model.library",
    "model_from_mesh": "model.library",
    "InvariantLoss": "loss.invariant",
    "PhotoTarget": "loss.invariant",
    "invariant_loss": "loss.invariant",
    "Mesh": "model.mesh",
    "load_mesh": "model.loading",
    "decode_photo": "photo",
    "load_photo": "photo",
    "load_photo_focal": "photo",
    "read_focal": "photo",
    "ExifFocal": "photo",
    "RegistrationOptions": "registration.options",
    "Pyramid": "registration.options",
    "Segmentation": "registration.options",
    "Terms": "registration.options",
    "Structure": "registration.options",
    "Budgets": "registration.options",
    "Probes": "registration.options",
    "Search": "registration.options",
    "RegistrationResult": "registration.result",
    "register": "registration.register",
    "ModelStore": "model.store",
    "Theta": "geometry.pose",
    "camera_to_theta": "geometry.pose",
    "theta_to_camera": "geometry.pose",
}

if TYPE_CHECKING:
    from vehicle_pose.errors import (
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
    from vehicle_pose.geometry.camera import Camera
    from vehicle_pose.geometry.pose import Theta, camera_to_theta, theta_to_camera
    from vehicle_pose.loss.invariant import InvariantLoss, PhotoTarget, invariant_loss
    from vehicle_pose.model.library import ModelLibrary, VehicleModel, model_from_mesh
    from vehicle_pose.model.loading import load_mesh
    from vehicle_pose.model.mesh import Mesh
    from vehicle_pose.model.store import ModelStore
    from vehicle_pose.photo import ExifFocal, decode_photo, load_photo, load_photo_focal, read_focal
    from vehicle_pose.registration.options import (
        Budgets,
        Probes,
        Pyramid,
        RegistrationOptions,
        Search,
        Segmentation,
        Structure,
        Terms,
    )
    from vehicle_pose.registration.register import register
    from vehicle_pose.registration.result import RegistrationResult


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
    "Budgets",
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
    "Probes",
    "Pyramid",
    "RegistrationOptions",
    "RegistrationResult",
    "RenderError",
    "Search",
    "Segmentation",
    "Structure",
    "Terms",
    "Theta",
    "UnknownModelError",
    "VehicleModel",
    "VehiclePoseError",
    "camera_to_theta",
    "decode_photo",
    "invariant_loss",
    "load_mesh",
    "load_photo",
    "load_photo_focal",
    "read_focal",
    "ExifFocal",
    "model_from_mesh",
    "register",
    "theta_to_camera",
]
