"""Helpers shared by the tests: synthetic ground truth made by the project's own code."""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from vehicle_pose import metrics
from vehicle_pose.geometry.camera import Camera, look_at_camera
from vehicle_pose.model.library import VehicleModel
from vehicle_pose.model.mesh import Mesh, Part
from vehicle_pose.model.metadata import parse_axis


def mesh_from_trimesh(tm: trimesh.Trimesh, kind: str = "body") -> Mesh:
    """A one-part mesh of ``kind`` with the trimesh's vertices, normals and faces, albedo 1."""
    return Mesh(
        (
            Part(
                "part",
                kind,
                np.asarray(tm.vertices, np.float64),
                np.asarray(tm.vertex_normals, np.float32),
                np.asarray(tm.faces, np.uint32),
                np.ones(len(tm.vertices), np.float32),
            ),
        )
    )


def view(model: VehicleModel, azimuth: float, elevation: float, *, distance: float = 9.0, focal: float = 900.0,
         width: int = 640, height: int = 480) -> Camera:
    """A camera looking at the model's centre from ``azimuth`` and ``elevation`` (degrees)."""
    centre, _ = model.mesh.sphere
    return look_at_camera(
        centre, parse_axis(model.info.forward), parse_axis(model.info.up),
        azimuth_deg=azimuth, elevation_deg=elevation, distance=distance, focal=focal, width=width, height=height,
    )


def perturbed(truth: Camera, seed: int, *, degrees: float = 6.0, shift: float = 0.03, focal: float = 0.1) -> Camera:
    """A rough start: rotated by ``degrees``, moved by ``shift`` of the distance, focal off."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    rot = Rotation.from_rotvec(np.radians(degrees) * axis / np.linalg.norm(axis)).as_matrix()
    t = truth.t + shift * np.linalg.norm(truth.t) * rng.normal(size=3) / np.sqrt(3)
    K = truth.K.copy()
    K[0, 0] *= 1 + focal
    K[1, 1] *= 1 + focal
    return Camera(K, rot @ truth.R, t, truth.width, truth.height)


def projection_error(model: VehicleModel, est: Camera, truth: Camera) -> float:
    """Mean distance (pixels) between 3000 surface points of the model projected by two cameras."""
    return metrics.projection_error(model.mesh.sample_points(3000), est, truth)
