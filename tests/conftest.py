"""Shared fixtures: one GL context per test session, the shipped sedan, synthetic ground truth."""

from __future__ import annotations

import pytest

from vehicle_pose.model.library import ModelLibrary, VehicleModel
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


@pytest.fixture(scope="session")
def library() -> ModelLibrary:
    return ModelLibrary()
