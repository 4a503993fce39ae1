"""Wheel metadata estimated from the mesh."""

from __future__ import annotations

import numpy as np
import pytest

from vehicle_pose.model.metadata import estimate_wheels, parse_axis


def test_wheel_estimate_matches_the_generator(sedan):
    est = estimate_wheels(sedan.mesh.vertices, parse_axis("+z"), parse_axis("+x"))
    true = sedan.wheels
    assert np.linalg.norm(est.rear_axle_center - true.rear_axle_center) < 0.03
    assert np.linalg.norm(est.front_axle_center - true.front_axle_center) < 0.03
    assert est.wheel_radius == pytest.approx(true.wheel_radius, rel=0.05)
    assert est.track_width == pytest.approx(true.track_width, rel=0.05)
