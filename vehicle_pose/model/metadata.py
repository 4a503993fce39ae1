"""Vehicle model metadata (method.md §4) and its estimation from the mesh.

A model's JSON file names its mesh and gives, in the mesh's own coordinates and units, the rear
and front axle centres, the axle direction (towards the vehicle's left), the track width and the
wheel radius. Whatever is missing is estimated from the mesh, given its up and forward axes, and
listed in ``estimated``.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from vehicle_pose.errors import ModelError
from vehicle_pose.geometry.pose import Side, SideGeometry
from vehicle_pose.model.mesh import column_bounds

__all__ = ["UNITS", "WHEEL_ESTIMATE", "WheelGeometry", "ModelInfo", "parse_axis", "estimate_wheels", "wheel_components"]

FloatArray = npt.NDArray[np.float64]
_AXES = {"x": 0, "y": 1, "z": 2}


WHEEL_ESTIMATE = 2
"""Version of the wheel estimate; raise it whenever :func:`estimate_wheels` gives other wheels
for a mesh (prepared models keep their estimate under it)."""

UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254, "ft": 0.3048}
"""Metres per unit of the length units a mesh may be given in."""


def parse_axis(text: str) -> FloatArray:
    """A signed axis such as ``+z`` or ``-y`` as a unit vector (3,)."""
    s = str(text).strip().lower()
    sign = -1.0 if s.startswith("-") else 1.0
    name = s.lstrip("+-")
    if name not in _AXES or len(s) - len(name) > 1:
        raise ModelError(f"axis {text!r} is not one of +x, -x, +y, -y, +z, -z")
    v = np.zeros(3)
    v[_AXES[name]] = sign
    return v


@dataclass(frozen=True)
class WheelGeometry:
    """Axle geometry in mesh coordinates and units.

    Attributes
    ----------
    rear_axle_center, front_axle_center : (3,) float64
        Midpoints between the left and right wheel centres of each axle.
    axle_direction : (3,) float64
        Unit axle direction towards the vehicle's left.
    track_width : float
        Distance between the left and right wheel centres.
    wheel_radius : float
    """

    rear_axle_center: FloatArray
    front_axle_center: FloatArray
    axle_direction: FloatArray
    track_width: float
    wheel_radius: float

    def side(self, side: Side) -> SideGeometry:
        """Wheel centres and outward axle of one side; the axle is made orthogonal to the wheelbase."""
        left = np.asarray(self.axle_direction, dtype=np.float64)
        b = self.front_axle_center - self.rear_axle_center
        b = b / np.linalg.norm(b)
        left = left - (left @ b) * b
        left /= np.linalg.norm(left)
        a = left if side == "left" else -left
        half = 0.5 * self.track_width * a
        return SideGeometry(self.rear_axle_center + half, self.front_axle_center + half, a)

    def wheel_centres(self) -> FloatArray:
        """The four wheel centres (4, 3): rear-left, front-left, rear-right, front-right."""
        left, right = self.side("left"), self.side("right")
        return np.stack([left.rear, left.front, right.rear, right.front])

    def to_dict(self) -> dict[str, Any]:
        return {
            "rear_axle_center": np.asarray(self.rear_axle_center).tolist(),
            "front_axle_center": np.asarray(self.front_axle_center).tolist(),
            "axle_direction": np.asarray(self.axle_direction).tolist(),
            "track_width": float(self.track_width),
            "wheel_radius": float(self.wheel_radius),
        }

    @classmethod
    def from_dict(cls, w: dict[str, Any]) -> WheelGeometry:
        """The inverse of :meth:`to_dict`."""
        return cls(
            np.asarray(w["rear_axle_center"], np.float64),
            np.asarray(w["front_axle_center"], np.float64),
            np.asarray(w["axle_direction"], np.float64),
            float(w["track_width"]),
            float(w["wheel_radius"]),
        )


_WHEEL_KEYS = ("rear_axle_center", "front_axle_center", "axle_direction", "track_width", "wheel_radius")


def estimate_wheels(vertices: npt.ArrayLike, up: FloatArray, forward: FloatArray,
                    parts: Sequence[tuple[npt.ArrayLike, npt.ArrayLike]] = ()) -> WheelGeometry:
    """Estimate the axle geometry of a car-like mesh.

    Where the mesh's ``parts`` (each ``(vertices, faces)``) model the tyres as pieces of their
    own, as CAD models do, the wheels are those pieces (:func:`wheel_components`). Otherwise, from
    the vertices alone: the lower envelope of the side view (height of the lowest vertex along
    the vehicle's length) touches the ground under each wheel; the contact points give the axle
    positions and the curvature of the envelope around them the wheel radius. The lateral
    spread of the vertices inside the wheel circles gives the track. The envelope is only as
    round as the tyre's polygon: a tyre of a few dozen faces reads as a smaller wheel (a CAD
    car's 0.071 as 0.040), which is why the pieces come first.

    Parameters
    ----------
    vertices : (N, 3)
        Mesh vertices, mesh frame.
    up, forward : (3,)
        Unit vectors of the vehicle's up and forward directions in the mesh frame.
    parts : sequence of ((V, 3), (F, 3)), optional
        The mesh's parts as vertices and faces, for :func:`wheel_components`.
    """
    if len(parts):
        found = wheel_components(parts, up, forward)
        if found is not None:
            return found
    v = np.asarray(vertices, dtype=np.float64)
    up = np.asarray(up, np.float64)
    fwd = np.asarray(forward, np.float64)
    left = np.cross(up, fwd)
    x, y, z = v @ fwd, v @ left, v @ up
    if len(v) < 8 or np.ptp(x) <= 0 or np.ptp(z) <= 0:
        raise ModelError("cannot estimate wheels: the mesh has no extent along its forward or up axis")
    length = float(np.ptp(x))
    ground = float(z.min())
    x_mid = 0.5 * (x.min() + x.max())
    y_mid = 0.5 * (y.min() + y.max())
    bins = np.linspace(x.min(), x.max(), 201)
    idx = np.clip(np.digitize(x, bins) - 1, 0, 199)
    env = np.full(200, np.inf)
    np.minimum.at(env, idx, z - ground)
    centres_x = 0.5 * (bins[:-1] + bins[1:])
    ok = np.isfinite(env)
    tol = 0.01 * length

    def contact(half: npt.NDArray[np.bool_]) -> float:
        sel = half & ok
        lowest = env[sel].min()
        xs = centres_x[sel][env[sel] <= lowest + tol]
        return float(np.median(xs))

    rear_x = contact(centres_x < x_mid)
    front_x = contact(centres_x >= x_mid)

    h_all = z - ground

    def radius(xc: float) -> float:
        r = 0.07 * length
        for _ in range(4):
            near = (np.abs(x - xc) < 0.8 * r) & (h_all < r)
            hull = _lower_hull(np.column_stack([x[near] - xc, h_all[near]]))
            hull = hull[hull[:, 1] > 0.004 * length]
            if len(hull) < 2:
                break
            d, h = hull[:, 0], hull[:, 1]
            r = float(np.median((d * d + h * h) / (2.0 * h)))
        return float(np.clip(r, 0.03 * length, 0.15 * length))

    r_rear, r_front = radius(rear_x), radius(front_x)
    wheel_r = 0.5 * (r_rear + r_front)

    def lateral(xc: float) -> float:
        inside = ((x - xc) ** 2 + (z - ground - wheel_r) ** 2 < (0.95 * wheel_r) ** 2) & (z < ground + wheel_r)
        ys = np.abs(y[inside] - y_mid)
        if ys.size < 4:
            return 0.4 * float(np.ptp(y))
        outer = ys[ys > 0.5 * ys.max()]
        return float(0.5 * (outer.min() + outer.max()))

    half_track = 0.5 * (lateral(rear_x) + lateral(front_x))
    height = ground + wheel_r

    def point(xc: float) -> FloatArray:
        p: FloatArray = xc * fwd + y_mid * left + height * up
        return p

    return WheelGeometry(point(rear_x), point(front_x), left, 2.0 * half_track, wheel_r)


_TYRE_DIAMETER = (0.08, 0.24)
"""A tyre's diameter as a share of the vehicle's length (cars, vans and pickups: 0.12-0.19)."""


def _pieces(points: FloatArray, faces: npt.NDArray[np.int64], grid: float
            ) -> tuple[FloatArray, npt.NDArray[np.int64]]:
    """The corners ``faces`` use, welded by position (to ``grid``), and the connected piece of
    each: faces that share a corner's position are one piece, so that a flat-shaded surface,
    whose faces each repeat their corners, stays whole. Returns the welded corners' points
    (C, 3) and their pieces (C,)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    # Only the corners the faces use, as one integer a position (21 bits an axis, the grid
    # coarse enough for the part's extent).
    used = np.zeros(len(points), bool)
    used[faces.reshape(-1)] = True
    index = np.flatnonzero(used)
    points = points[index]
    origin, top = column_bounds(points)
    grid = max(grid, float((top - origin).max()) / float(1 << 20))
    cells = ((points - origin) * (1.0 / grid)).astype(np.int64)
    key = (cells[:, 0] << 42) | (cells[:, 1] << 21) | cells[:, 2]
    _, first, welded_used = np.unique(key, return_index=True, return_inverse=True)
    welded = np.zeros(len(used), np.int64)
    welded[index] = welded_used.reshape(-1)
    corner = welded[faces]  # (F, 3) welded corner ids
    n = len(first)
    a = np.concatenate([corner[:, 0], corner[:, 1]])
    b = np.concatenate([corner[:, 1], corner[:, 2]])
    graph = coo_matrix((np.ones(a.size, np.int8), (a, b)), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    return points[first], label.astype(np.int64)


def wheel_components(parts: Sequence[tuple[npt.ArrayLike, npt.ArrayLike]], up: FloatArray,
                     forward: FloatArray) -> WheelGeometry | None:
    """The wheels of a mesh that models its tyres as pieces of their own, or None.

    A tyre is a connected piece of the mesh (faces sharing corners, within one part) that is
    round seen from the side (as long as it is high, within 20 %), stands on the ground (its
    bottom within 3 % of the vehicle's length of the mesh's lowest point), is narrower than half
    its diameter, lies off the vehicle's middle, and is 8-24 % of the vehicle's length across.
    The largest such piece in each corner of the vehicle (front or rear, left or right) is its
    wheel: a rim or a hub inside the tyre is smaller. With a wheel found at the front and at the
    rear, the axle centres are the means of their wheels' centres (on the vehicle's middle line),
    the radius their median half diameter and the track the mean distance between an axle's
    left and right wheels (twice the found wheel's offset where only one side has one).
    None where the front or the rear has no such piece (a body whose tyres are welded to it):
    such meshes are left to the envelope of :func:`estimate_wheels`.
    """
    up = np.asarray(up, np.float64)
    fwd = np.asarray(forward, np.float64)
    left = np.cross(up, fwd)
    frame = np.stack([fwd, left, up])
    shapes = [(np.asarray(v, np.float64).reshape(-1, 3), np.asarray(f, np.int64).reshape(-1, 3)) for v, f in parts]
    shapes = [(v, f) for v, f in shapes if len(f)]
    if not shapes:
        return None
    locals_ = [v @ frame.T for v, _ in shapes]
    bounds = [column_bounds(loc) for loc in locals_]
    lo, hi = np.min([b[0] for b in bounds], axis=0), np.max([b[1] for b in bounds], axis=0)
    length = float(hi[0] - lo[0])
    if length <= 0.0:
        return None
    mid = 0.5 * (lo + hi)
    half_width = 0.5 * float(hi[1] - lo[1])
    found: list[FloatArray] = []  # per piece: centre (3,), diameter
    for local, (_, f) in zip(locals_, shapes, strict=True):
        # Only faces low enough and far enough from the middle line to belong to a wheel: a
        # piece cut by these lines is too tall, or as long as the car, to be one.
        near = (local[:, 2] < lo[2] + 0.3 * length) & (np.abs(local[:, 1] - mid[1]) > 0.2 * half_width)
        low = f[near[f[:, 0]] & near[f[:, 1]] & near[f[:, 2]]]
        if not len(low):
            continue
        points, pieces = _pieces(local, low, 1e-6 * length)
        order = np.argsort(pieces, kind="stable")
        starts = np.flatnonzero(np.r_[True, np.diff(pieces[order]) != 0])
        pmin = np.minimum.reduceat(points[order], starts, axis=0)
        pmax = np.maximum.reduceat(points[order], starts, axis=0)
        size = pmax - pmin
        across = np.maximum(size[:, 0], size[:, 2])  # a polygon's corners lie on the circle
        centre = 0.5 * (pmin + pmax)
        keep = ((size[:, 0] > 0.8 * size[:, 2]) & (size[:, 0] < 1.25 * size[:, 2])
                & (across > _TYRE_DIAMETER[0] * length) & (across < _TYRE_DIAMETER[1] * length)
                & (pmin[:, 2] < lo[2] + 0.03 * length) & (size[:, 1] < 0.5 * across)
                & (np.abs(centre[:, 1] - mid[1]) > 0.3 * half_width))
        found += [np.r_[c, d] for c, d in zip(centre[keep], across[keep], strict=True)]
    corners_found: dict[tuple[bool, bool], FloatArray] = {}
    for piece in found:
        key = (bool(piece[0] > mid[0]), bool(piece[1] > mid[1]))
        if key not in corners_found or piece[3] > corners_found[key][3]:
            corners_found[key] = piece
    axles = []
    for front in (False, True):
        wheels = [p for (fr, _), p in corners_found.items() if fr == front]
        if not wheels:
            return None
        axles.append(wheels)
    radius = 0.5 * float(np.median([p[3] for w in axles for p in w]))
    offsets = [abs(float(p[1] - mid[1])) for w in axles for p in w]
    tracks = [abs(float(w[0][1] - w[1][1])) for w in axles if len(w) == 2]
    track = float(np.mean(tracks)) if tracks else 2.0 * float(np.mean(offsets))

    def axle(wheels: list[FloatArray]) -> FloatArray:
        x, z = float(np.mean([p[0] for p in wheels])), float(np.mean([p[2] for p in wheels]))
        point: FloatArray = np.array([x, mid[1], z]) @ frame
        return point

    return WheelGeometry(axle(axles[0]), axle(axles[1]), left, track, radius)


def _lower_hull(points: FloatArray) -> FloatArray:
    """Lower convex hull (monotone chain) of 2-D points (N, 2), sorted by x.

    A point equal to the last one on the chain pops it (their cross product is exactly 0) and
    takes its place after the same test that placed it, so repeated points (a flat-shaded mesh
    repeats each vertex for every face around it) are dropped first: the same hull, sooner. (The
    one exception: copies of a single point, which the chain keeps two of.)"""
    pts = points[np.lexsort((points[:, 1], points[:, 0]))]
    if len(pts) > 1:
        distinct = pts[np.r_[True, (pts[1:] != pts[:-1]).any(axis=1)]]
        pts = distinct if len(distinct) > 1 else pts[:2]
    hull: list[FloatArray] = []
    for pt in pts:
        while len(hull) >= 2:
            (x1, y1), (x2, y2) = hull[-2], hull[-1]
            if (x2 - x1) * (pt[1] - y1) - (y2 - y1) * (pt[0] - x1) <= 0:
                hull.pop()
            else:
                break
        hull.append(pt)
    return np.array(hull).reshape(-1, 2)


@dataclass(frozen=True)
class ModelInfo:
    """What the library knows of one vehicle model.

    ``mesh_path`` is absolute; ``estimated`` lists the metadata fields estimated from the mesh;
    ``parts_path`` is the model's part file (``parts`` in the metadata, relative to it; each
    face's part, :func:`~vehicle_pose.model.parts.read_part_file`), None without one.
    """

    id: str
    name: str
    mesh_path: Path
    units: str
    meters_per_unit: float
    up: str
    forward: str
    wheels: WheelGeometry | None
    estimated: tuple[str, ...] = ()
    texture_dirs: tuple[Path, ...] = ()
    extra: dict[str, Any] = field(default_factory=dict)
    parts_path: Path | None = None

    @classmethod
    def from_json(cls, path: str | Path) -> ModelInfo:
        """Read a model's metadata file; the mesh path is relative to the file."""
        p = Path(path)
        try:
            data = json.loads(p.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise ModelError(f"cannot read model metadata {p}: {exc}") from None
        return cls.from_dict(data, base=p.parent)

    @classmethod
    def from_dict(cls, data: dict[str, Any], *, base: Path) -> ModelInfo:
        for key in ("id", "mesh"):
            if key not in data:
                raise ModelError(f"model metadata lacks {key!r}")
        w = data.get("wheels") or {}
        wheels = WheelGeometry.from_dict(w) if all(k in w for k in _WHEEL_KEYS) else None
        known = {"id", "name", "mesh", "units", "meters_per_unit", "up", "forward", "wheels", "estimated",
                 "texture_dirs", "parts"}
        return cls(
            id=str(data["id"]),
            name=str(data.get("name", data["id"])),
            mesh_path=(base / data["mesh"]).resolve(),
            units=str(data.get("units", "m")),
            meters_per_unit=float(data.get("meters_per_unit", 1.0)),
            up=str(data.get("up", "+z")),
            forward=str(data.get("forward", "+x")),
            wheels=wheels,
            estimated=tuple(data.get("estimated", ())),
            texture_dirs=tuple((base / d).resolve() for d in data.get("texture_dirs", ())),
            extra={k: v for k, v in data.items() if k not in known},
            parts_path=(base / data["parts"]).resolve() if data.get("parts") else None,
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "name": self.name,
            "mesh": str(self.mesh_path),
            "units": self.units,
            "meters_per_unit": self.meters_per_unit,
            "up": self.up,
            "forward": self.forward,
            "wheels": self.wheels.to_dict() if self.wheels is not None else None,
            "estimated": list(self.estimated),
        } | ({"parts": str(self.parts_path)} if self.parts_path is not None else {})
