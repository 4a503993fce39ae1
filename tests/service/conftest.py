"""Fixtures of the service tests: the whole service, started once per session, and a photo
with its truth and a rough start."""

from __future__ import annotations

import pytest

from vehicle_pose.render.synth import LIGHTINGS, synthesize

from helpers import perturbed, view


@pytest.fixture(scope="session")
def service(tmp_path_factory):
    """The whole service, started once for the test session (real Redis, Celery, uvicorn)."""
    from service_stack import start_stack

    stack = start_stack(tmp_path_factory.mktemp("service"))
    yield stack
    stack.stop()


@pytest.fixture(scope="module")
def scene(sedan, renderer):
    """A synthetic 640x480 photo of the sedan at a known pose and a rough start camera."""
    truth = view(sedan, 65.0, 18.0, focal=950.0)
    photo, _ = synthesize(sedan.mesh, truth, lighting=LIGHTINGS["side"], renderer=renderer, seed=5)
    return photo, truth, perturbed(truth, 5)
