"""Start poses from the wheels: ellipses found where the wheels project, a pair's start near the truth."""

from __future__ import annotations

import numpy as np
import pytest

from vehicle_pose.metrics import rotation_error
from vehicle_pose.render.synth import LIGHTINGS, synthesize
from vehicle_pose.search.views import (
    score_cameras,
)
from vehicle_pose.search.wheels import detect_wheels, wheel_candidates
from vehicle_pose.segment.region import find_vehicle

from helpers import view


@pytest.mark.parametrize("azimuth,elevation", [(75.0, 6.0), (250.0, 10.0)])
def test_wheel_ellipses_found_where_the_wheels_project(library, renderer, azimuth, elevation):
    sedan = library.load("sedan")
    truth = view(sedan, azimuth, elevation, focal=1200.0, distance=11.0)
    photo, mask = synthesize(sedan.mesh, truth, lighting=LIGHTINGS["front"], renderer=renderer, seed=5)
    side = "left" if azimuth < 180 else "right"
    geometry = sedan.wheels.side(side)
    ellipses = detect_wheels(photo, find_vehicle(photo))
    up, fwd = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])
    ring = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    for centre in (geometry.rear, geometry.front):
        c = truth.project(centre[None])[0]
        rim = centre + sedan.wheels.wheel_radius * (np.cos(ring)[:, None] * fwd + np.sin(ring)[:, None] * up)
        radius_px = 0.5 * np.ptp(truth.project(rim)[:, 1])
        near = [e for e in ellipses if np.hypot(*(np.array(e.centre) - c)) < 0.35 * radius_px]
        assert near, f"no ellipse near the projected wheel at {c}: {[e.to_dict() for e in ellipses]}"
        e = near[0]
        assert 0.8 < e.a / radius_px < 1.3
        # The axis ratio is the cosine of the axle's angle to the line of sight.
        psi = truth.R @ geometry.axle
        assert abs(e.b / e.a - abs(psi[2]) / np.linalg.norm(psi)) < 0.15


def test_wheel_pair_gives_a_start_near_the_truth(library, renderer):
    sedan = library.load("sedan")
    truth = view(sedan, 100.0, 8.0, focal=1200.0, distance=11.0)
    photo, _ = synthesize(sedan.mesh, truth, renderer=renderer, seed=6)
    region = find_vehicle(photo)
    cands = wheel_candidates(detect_wheels(photo, region), sedan, 640, 480)
    assert cands and all(c.source == "wheels" for c in cands)
    best = score_cameras(photo, region, sedan, cands, renderer)[0]
    assert rotation_error(best.camera.R, truth.R) < 20.0
