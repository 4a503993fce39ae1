"""Shared fixtures: one GL context per test session, the shipped sedan, synthetic ground truth."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from vehicle_pose.geometry.camera import Camera, look_at_camera
from vehicle_pose.model.library import ModelLibrary, VehicleModel
from vehicle_pose.model.mesh import Mesh, Part
from vehicle_pose.model.metadata import parse_axis
from vehicle_pose.render.gl import get_context
from vehicle_pose.render.renderer import Renderer


@pytest.fixture(scope="session", autouse=True)
def _model_cache(tmp_path_factory):
    """Prepared models of this session (the CLI's and the service's, in subprocesses too) go
    to a temporary folder, never to the user's cache."""
    import os

    os.environ["VEHICLE_POSE_CACHE_DIR"] = str(tmp_path_factory.mktemp("model-cache"))
    yield


@pytest.fixture(scope="session")
def ctx():
    return get_context()


@pytest.fixture(scope="session")
def renderer(ctx):
    return Renderer(ctx)


@pytest.fixture(autouse=True)
def _no_gl_error(request):
    """Every test that used the GL context leaves no pending OpenGL error."""
    yield
    if "ctx" in request.fixturenames or "renderer" in request.fixturenames:
        assert get_context().error == "GL_NO_ERROR"


@pytest.fixture(scope="session")
def sedan() -> VehicleModel:
    return ModelLibrary().load("sedan")


def mesh_from_trimesh(tm: trimesh.Trimesh, kind: str = "body") -> Mesh:
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
    centre, _ = model.mesh.sphere
    return look_at_camera(
        centre, parse_axis(model.info.forward), parse_axis(model.info.up),
        azimuth_deg=azimuth, elevation_deg=elevation, distance=distance, focal=focal, width=width, height=height,
    )


def projection_error(model: VehicleModel, est: Camera, truth: Camera) -> float:
    """Mean distance (pixels) between the model's vertices projected by two cameras."""
    pts = model.mesh.sample_points(3000)
    return float(np.linalg.norm(est.project(pts) - truth.project(pts), axis=1).mean())


@pytest.fixture(scope="session")
def service(tmp_path_factory):
    """The whole service, started once for the test session (real Redis, Celery, uvicorn)."""
    from service_stack import start_stack

    stack = start_stack(tmp_path_factory.mktemp("service"))
    yield stack
    stack.stop()
