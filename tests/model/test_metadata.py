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


def _plain_lower_hull(points: np.ndarray) -> np.ndarray:
    pts = points[np.lexsort((points[:, 1], points[:, 0]))]
    hull: list[np.ndarray] = []
    for pt in pts:
        while len(hull) >= 2:
            (x1, y1), (x2, y2) = hull[-2], hull[-1]
            if (x2 - x1) * (pt[1] - y1) - (y2 - y1) * (pt[0] - x1) <= 0:
                hull.pop()
            else:
                break
        hull.append(pt)
    return np.array(hull).reshape(-1, 2)


def test_the_lower_hull_skips_repeated_points_and_stays_the_monotone_chain():
    from vehicle_pose.model.metadata import _lower_hull

    rng = np.random.default_rng(4)
    for trial in range(600):
        n = int(rng.integers(0, 25))
        points = rng.integers(-3, 4, (n, 2)).astype(float) if trial % 2 else rng.normal(size=(n, 2))
        if n:
            points = np.r_[points, points[rng.integers(0, n, int(rng.integers(0, 15)))]]
        np.testing.assert_array_equal(_lower_hull(points), _plain_lower_hull(points))
    one = np.array([[1.0, 2.0]] * 3)
    assert _lower_hull(one).shape == (2, 2)  # the chain keeps two copies of a lone point
