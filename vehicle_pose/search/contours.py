"""A sparse contour model: the model's edges as points on its surface, one set per view of a view
sphere, projected and scored against a photo's edges without rendering.

The structure's searches score thousands of poses by the directional chamfer of the model's
edges (outline, creases, material boundaries) against the photo's
(:class:`~vehicle_pose.loss.edges.EdgeLoss`); rendering each pose is most of their time on a
CPU. The region-based trackers that run in a millisecond a step (SRT3D, Stoiber et al. IJCV
2022; ICG, CVPR 2022) never render while they search: they keep a *sparse viewpoint model*, a
few hundred contour points with their directions for each view of a sphere of views, and
project the points of the view nearest the current camera. The same serves the chamfer:

- **Which edges a camera sees depends only on where it is** (its centre of projection relative
  to the model), not on where it looks or on its focal length: the outline is where the lines
  of sight graze the surface, and what hides a crease is what lies between it and the eye. So a
  view is chosen by the camera's position alone: its direction from the model's centre
  (azimuth and elevation, measured as the templates measure them) and its distance in
  bounding-sphere radii, each rounded to the nearest of a :class:`ContourGrid`. Which creases
  and small parts make an edge does depend on the size the model is seen at (a render at 320
  pixels shows the door gaps a render at 60 merges), so each view is drawn at the grid's scale
  nearest the camera's (the bounding sphere's radius in pixels, on a log scale).
- **A view's points** are drawn the first time a search needs them and kept for the process:
  the exterior level of detail is drawn from the view once with its attributes (whose changes
  between pixels are the edges, :func:`~vehicle_pose.loss.edges.model_edges`) and once with
  face ids; each edge pixel kept is put back on the surface (its ray met with the plane of the
  face it shows), with a second point one drawn pixel along the edge on the same plane, which
  gives the edge's direction in any projection. A search visits a few dozen views, so nothing
  is prepared beforehand.
- **Score** (:meth:`ContourModel.cost`): the view's points projected by the camera, each costing
  its distance to the photo's nearest edge of its orientation bin, truncated; the mean over the
  points inside the frame. A pose costs tens of microseconds instead of a render.

Between two views of the grid the outline slides a little along the surface: with views every
2.5 degrees of azimuth and 2 of elevation the projected points lie within a pixel of the
rendered edges, and the cost follows the rendered chamfer of poses 0.5-8 degrees off a
synthetic photo's truth to 0.006 on average (0.017 when every view is drawn at one scale;
``tests/search/test_contours.py``, ``docs/decisions/0023-sparse-contours.md``).
"""

from __future__ import annotations

import weakref
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from numba import njit

from vehicle_pose.clock import timed
from vehicle_pose.geometry.camera import Camera, look_at_camera
from vehicle_pose.loss.edges import ORIENTATIONS, model_edges
from vehicle_pose.model.library import VehicleModel
from vehicle_pose.model.mesh import Mesh
from vehicle_pose.model.parts import face_geometry
from vehicle_pose.render.parts import face_ids
from vehicle_pose.render.renderer import Renderer
from vehicle_pose.search.views import upright_axes

__all__ = ["ContourGrid", "ContourModel", "contour_model"]

FloatArray = npt.NDArray[np.float64]
View = tuple[int, int, int, int]  # indices of the distance, the elevation, the azimuth and the scale

_SEED = 20261204  # the edge pixels kept of each view: the same in every process


@dataclass(frozen=True)
class ContourGrid:
    """The views of a contour model: every ``azimuth_step`` degrees all round, every
    ``elevation_step`` degrees from ``elevations[0]`` to ``elevations[1]`` above the ground, each
    camera ``distance`` (bounding-sphere radii), and each drawn at each of ``scales`` (the
    bounding sphere's radius in pixels: which creases and small parts make edges depends on the
    size they are seen at); each keeps at most ``points`` edge points. ``crease`` and
    ``albedo_step`` say what makes an edge (:func:`~vehicle_pose.loss.edges.model_edges`). The
    ``kept`` views used last are kept in memory (a view is 10-60 kB)."""

    azimuth_step: float = 2.5
    elevation_step: float = 2.0
    elevations: tuple[float, float] = (-20.0, 60.0)
    distances: tuple[float, ...] = (2.5, 5.0, 10.0, 20.0, 40.0, 80.0)
    points: int = 5000
    scales: tuple[float, ...] = (20.0, 40.0, 80.0, 160.0)
    crease: float = 0.6
    albedo_step: float = 0.08
    kept: int = 2048

    def __post_init__(self) -> None:
        if not (0.5 <= self.azimuth_step <= 90.0 and 0.5 <= self.elevation_step <= 45.0) or not self.distances:
            raise ValueError(f"unusable contour grid {self}")
        if not (-89.0 <= self.elevations[0] <= self.elevations[1] <= 89.0):
            raise ValueError(f"unusable contour grid {self}")
        if min(self.distances) <= 1.05 or self.points < 8 or min(self.scales) < 8:
            raise ValueError(f"unusable contour grid {self}")


class ContourModel:
    """The sparse contour model of ``mesh`` (an exterior level of detail of ``model``) over
    ``grid``: see the module docstring. Use :func:`contour_model`, which keeps one per mesh."""

    def __init__(self, model: VehicleModel, mesh: Mesh, grid: ContourGrid = ContourGrid()) -> None:
        self.mesh, self.grid = mesh, grid
        self.centre, self.radius = model.mesh.sphere
        self.up, self.forward = upright_axes(model)
        self.left = np.cross(self.up, self.forward)
        tris, normals, _, _ = face_geometry(mesh)
        self._anchors, self._normals = tris[:, 0], normals
        self._logs = np.log(np.asarray(grid.distances, np.float64))
        self._scales = np.log(np.asarray(grid.scales, np.float64))
        lo, hi = grid.elevations
        self._elevations = lo + grid.elevation_step * np.arange(int(np.floor((hi - lo) / grid.elevation_step)) + 1)
        self._azimuths = int(round(360.0 / grid.azimuth_step))
        self._views: OrderedDict[View, tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]] = OrderedDict()

    @property
    def drawn(self) -> int:
        """How many views are kept drawn."""
        return len(self._views)

    def view(self, camera: Camera) -> View:
        """The view of the grid nearest ``camera``'s position: the nearest distance (on a log
        scale), elevation and azimuth; and the scale nearest the size it sees the model at."""
        v = camera.eye - self.centre
        norm = float(np.linalg.norm(v))
        if not np.isfinite(norm) or norm <= 0.0:
            raise ValueError("the camera stands at the model's centre")
        el = np.degrees(np.arcsin(np.clip(float(v @ self.up) / norm, -1.0, 1.0)))
        az = np.degrees(np.arctan2(float(v @ self.left), float(v @ self.forward)))
        seen = camera.focal * self.radius / norm  # the bounding sphere's radius in the image
        return (int(np.argmin(np.abs(self._logs - np.log(norm / self.radius)))),
                int(np.argmin(np.abs(self._elevations - el))),
                int(round(az / self.grid.azimuth_step)) % self._azimuths,
                int(np.argmin(np.abs(self._scales - np.log(max(seen, 1e-9))))))

    def points(self, view: View, renderer: Renderer) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
        """The edge points of ``view`` (N, 3) and, for each, a point one drawn pixel along its
        edge (N, 3), in mesh coordinates; drawn on first use, the ``grid.kept`` views last used
        kept."""
        found = self._views.get(view)
        if found is None:
            found = self._views[view] = self._draw(view, renderer)
            if len(self._views) > self.grid.kept:
                self._views.popitem(last=False)
        else:
            self._views.move_to_end(view)
        return found

    def _draw(self, view: View, renderer: Renderer) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
        g = self.grid
        d, el, az = g.distances[view[0]], float(self._elevations[view[1]]), view[2] * g.azimuth_step
        focal = g.scales[view[3]] * d
        half = int(np.ceil(focal * np.tan(np.arcsin(min(0.99, 1.0 / d))))) + 4
        cam = look_at_camera(self.centre, self.forward, self.up, azimuth_deg=az, elevation_deg=el,
                             distance=d * self.radius, focal=focal, width=2 * half + 1, height=2 * half + 1)
        frame = renderer.render(self.mesh, cam)
        edges = model_edges(frame, albedo_step=g.albedo_step, crease=g.crease)
        r, c = np.nonzero(edges >= 0)
        b = edges[r, c].astype(np.intp)
        r, c = r + frame.y0, c + frame.x0
        ids = face_ids(renderer, self.mesh, cam)[r, c] - 1
        keep = np.flatnonzero(ids >= 0)
        if keep.size > g.points:
            keep = np.sort(np.random.default_rng((_SEED, *view)).choice(keep, g.points, replace=False))
        r, c, b, ids = r[keep], c[keep], b[keep], ids[keep]
        # The gradient's direction at the middle of each point's bin; the edge runs a quarter turn from it.
        theta = (b + 0.5) * np.pi / ORIENTATIONS
        uv = np.stack([c, r], axis=1).astype(np.float64)
        p = _on_face(cam, uv, self._anchors[ids], self._normals[ids])
        q = _on_face(cam, uv + np.stack([-np.sin(theta), np.cos(theta)], axis=1), self._anchors[ids],
                     self._normals[ids])
        ok = np.all(np.isfinite(p), axis=1) & np.all(np.isfinite(q), axis=1)
        return np.ascontiguousarray(p[ok], np.float32), np.ascontiguousarray(q[ok], np.float32)

    @timed("chamfer")
    def cost(self, camera: Camera, distance: npt.NDArray[np.float32], tau: float, renderer: Renderer, *,
             min_points: int = 8) -> float:
        """The directional chamfer of the view nearest ``camera``: the mean over its points
        inside the frame of the distance (``distance``: (ORIENTATIONS, H, W), the photo's at
        the camera's size) to the photo's nearest edge of the point's orientation, truncated
        at ``tau`` pixels, over ``tau``; 1 where fewer than ``min_points`` are inside."""
        p, q = self.points(self.view(camera), renderer)
        total, count = _project_cost(p, q, camera.R, camera.t, camera.K, distance, float(tau))
        if count < min_points:
            return 1.0
        return float(total / count / tau)

    def project(self, camera: Camera, renderer: Renderer) -> tuple[FloatArray, npt.NDArray[np.intp]]:
        """The nearest view's points as ``camera`` sees them (N, 2) and their orientation bins
        (N,), those behind the camera left out (for tests and pictures)."""
        p, q = self.points(self.view(camera), renderer)
        ok = (camera.to_camera(p)[:, 2] > 1e-9) & (camera.to_camera(q)[:, 2] > 1e-9)
        uv, uq = camera.project(p[ok]), camera.project(q[ok])
        d = uq - uv
        theta = np.mod(np.arctan2(-d[:, 0], d[:, 1]), np.pi)  # the gradient, a quarter turn from the edge
        return uv, np.minimum((theta / np.pi * ORIENTATIONS).astype(np.intp), ORIENTATIONS - 1)


_MODELS: weakref.WeakKeyDictionary[Mesh, dict[ContourGrid, ContourModel]] = weakref.WeakKeyDictionary()


def contour_model(model: VehicleModel, faces: int, renderer: Renderer, grid: ContourGrid = ContourGrid()
                  ) -> ContourModel:
    """The contour model of ``model``'s exterior level of ``faces`` over ``grid`` (its views
    drawn as they are needed, kept as long as the level is)."""
    mesh = model.exterior(faces, renderer)
    kept = _MODELS.setdefault(mesh, {})
    found = kept.get(grid)
    if found is None:
        found = kept[grid] = ContourModel(model, mesh, grid)
    return found


def _on_face(camera: Camera, uv: FloatArray, anchor: FloatArray, normal: FloatArray) -> FloatArray:
    """Where the rays through pixels ``uv`` (N, 2) meet the planes through ``anchor`` with
    ``normal`` (N, 3 each, mesh coordinates); NaN where a ray runs along its plane."""
    K = camera.K
    rays = np.stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(uv))], axis=1)
    rays = rays @ camera.R  # to mesh coordinates (R^T applied to each)
    eye = camera.eye
    den = np.sum(rays * normal, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.sum((anchor - eye) * normal, axis=1) / den
    out: FloatArray = eye + s[:, None] * rays
    out[np.abs(den) < 1e-9] = np.nan
    return out


@njit(cache=True, nogil=True)
def _project_cost(points: Any, along: Any, R: Any, t: Any, K: Any, distance: Any,
                  tau: float) -> tuple[float, int]:  # pragma: no cover - compiled
    """The sum of the truncated distances of ``points`` projected by ``(K, R, t)``,
    each looked up in the plane of its orientation bin, and how many fell inside the frame."""
    bins, H, W = distance.shape
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    total = 0.0
    count = 0
    for p in range(points.shape[0]):
        x, y, z = points[p, 0], points[p, 1], points[p, 2]
        X = R[0, 0] * x + R[0, 1] * y + R[0, 2] * z + t[0]
        Y = R[1, 0] * x + R[1, 1] * y + R[1, 2] * z + t[1]
        Z = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z + t[2]
        if Z <= 1e-9:
            continue
        u, v = fx * X / Z + cx, fy * Y / Z + cy
        c = int(np.floor(u + 0.5))
        r = int(np.floor(v + 0.5))
        if c < 0 or r < 0 or c >= W or r >= H:
            continue
        x, y, z = along[p, 0], along[p, 1], along[p, 2]
        X = R[0, 0] * x + R[0, 1] * y + R[0, 2] * z + t[0]
        Y = R[1, 0] * x + R[1, 1] * y + R[1, 2] * z + t[1]
        Z = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z + t[2]
        if Z <= 1e-9:
            continue
        du, dv = fx * X / Z + cx - u, fy * Y / Z + cy - v
        # The gradient is a quarter turn from the edge: (dv, -du), its angle modulo pi.
        theta = np.arctan2(-du, dv)
        if theta < 0.0:
            theta += np.pi
        b = min(int(theta / np.pi * bins), bins - 1)
        d = distance[b, r, c]
        total += d if d < tau else tau
        count += 1
    return total, count
