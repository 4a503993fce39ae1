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


def _prism(centre: np.ndarray, radius: float, width: float, sides: int) -> tuple[np.ndarray, np.ndarray]:
    """A tyre as a CAD model draws it: a prism of ``sides`` faces about the y axis, flat shaded
    (every triangle with corners of its own), in a +z up, +x forward frame."""
    t = np.linspace(0.0, 2.0 * np.pi, sides, endpoint=False)  # a flat bottom, corners at the front and back
    ring = np.stack([radius * np.cos(t), np.zeros(sides), radius * np.sin(t)], axis=1)
    outer, inner = ring + [0.0, 0.5 * width, 0.0], ring - [0.0, 0.5 * width, 0.0]
    tris = []
    for k in range(sides):
        j = (k + 1) % sides
        tris += [(outer[k], outer[j], inner[k]), (outer[j], inner[j], inner[k])]
        tris += [(np.array([0.0, 0.5 * width, 0.0]), outer[k], outer[j])]
        tris += [(np.array([0.0, -0.5 * width, 0.0]), inner[j], inner[k])]
    vertices = np.asarray(tris, np.float64).reshape(-1, 3) + centre
    return vertices, np.arange(len(vertices)).reshape(-1, 3)


def _box(lo: list[float], hi: list[float]) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    box = trimesh.creation.box(bounds=[lo, hi])
    return np.asarray(box.vertices), np.asarray(box.faces)


def test_tyres_modelled_as_pieces_are_the_wheels():
    """A CAD car whose four tyres are coarse, flat-shaded prisms of one part, apart from the
    body: the wheels are the pieces, exactly."""
    from vehicle_pose.model.metadata import wheel_components

    radius, axles, half_track = 0.33, (-1.35, 1.4), 0.74
    tyres = [_prism(np.array([x, y, radius]), radius, 0.22, 8) for x in axles for y in (-half_track, half_track)]
    wheels = (np.concatenate([v for v, _ in tyres]),
              np.concatenate([f + sum(len(v) for v, _ in tyres[:k]) for k, (_, f) in enumerate(tyres)]))
    body = _box([-2.1, -0.85, 0.3], [2.2, 0.85, 1.4])
    up, fwd = parse_axis("+z"), parse_axis("+x")

    found = wheel_components([body, wheels], up, fwd)
    assert found is not None
    assert found.wheel_radius == pytest.approx(radius, rel=0.01)
    np.testing.assert_allclose(found.rear_axle_center, [axles[0], 0.0, radius], atol=0.01)
    np.testing.assert_allclose(found.front_axle_center, [axles[1], 0.0, radius], atol=0.01)
    assert found.track_width == pytest.approx(2 * half_track, rel=0.01)
    assert estimate_wheels(np.concatenate([body[0], wheels[0]]), up, fwd, [body, wheels]).to_dict() == found.to_dict()


def test_a_mesh_without_tyre_pieces_front_and_rear_is_left_to_the_envelope(sedan):
    """No piece stands on the ground at the front and at the rear: the estimate is the envelope's."""
    from vehicle_pose.model.metadata import wheel_components

    up, fwd = parse_axis("+z"), parse_axis("+x")
    shell = [(p.vertices, p.faces) for p in sedan.mesh.parts if p.name in ("body", "glass")]
    assert wheel_components(shell, up, fwd) is None
    rear_only = [(p.vertices, p.faces) for p in sedan.mesh.parts if not p.name.endswith(("fr", "fl"))]
    assert wheel_components(rear_only, up, fwd) is None
    vertices = sedan.mesh.vertices
    assert estimate_wheels(vertices, up, fwd, rear_only).to_dict() == estimate_wheels(vertices, up, fwd).to_dict()


@pytest.mark.parametrize("name", ["sedan", "hatchback", "pickup", "suv", "van"])
def test_the_shipped_models_tyres_give_their_wheels(library, name):
    from vehicle_pose.model.metadata import wheel_components

    model = library.load(name)
    found = wheel_components([(p.vertices, p.faces) for p in model.mesh.parts], parse_axis(model.info.up),
                             parse_axis(model.info.forward))
    true = model.wheels
    assert found is not None
    np.testing.assert_allclose(found.rear_axle_center, true.rear_axle_center, atol=1e-3)
    np.testing.assert_allclose(found.front_axle_center, true.front_axle_center, atol=1e-3)
    assert found.wheel_radius == pytest.approx(true.wheel_radius, rel=1e-3)
    assert found.track_width == pytest.approx(true.track_width, rel=1e-3)
