"""Edge templates of a model over a view sphere, matched to a photo's edges with their place and scale.

Edge-based template matching finds a known rigid object in clutter without training: the
object's edges are drawn once from many views, and each drawing is slid over the photo's
distance transform, a placement costing the mean distance from its edge points to the photo's
nearest edge of the same orientation (the directional chamfer of Fast Directional Chamfer
Matching, Liu et al. CVPR 2010, which made it the standard for shiny objects in clutter; the
gradient response maps of LINE-2D, Hinterstoisser et al. PAMI 2012, score the same points by
orientation). Here:

- **Templates** (:meth:`ViewTemplates.build`, once per model, kept in the prepared-model
  store): the exterior level of detail rendered from every view of a :class:`TemplateGrid`
  (azimuths all round, a few elevations, a few camera distances, which set the perspective),
  looking at the model's centre; each view keeps up to ``points`` of its edge pixels (outline,
  creases, material boundaries) with their orientation bins, in normalised image coordinates
  (pixel offset from the centre's image over the focal length), and the box of its projection.
- **Placement**: scaling a template by a focal length ``f`` (pixels) and moving the centre's
  image to ``(u, v)`` is, up to the small change of perspective off the optical axis, the view
  of a camera with that focal length, turned so that its axis-to-centre ray passes through
  ``(u, v)`` (:meth:`ViewTemplates.camera`).
- **Matching** (:func:`match`): every allowed template is tried at scales and positions about
  each target box (the client's box, the photo's frame, a region found in it), kept where its
  projection cut to the frame overlaps the box by ``min_iou``; a template cut by the frame is
  scored on its points inside (beyond the border nothing is known), so that a car cut by the
  border is a template cut by the border and not a failure; at least ``min_seen`` of its
  points must be in view. Each point is projected exactly as the placed camera sees it, the
  template's rays turned with the camera, so a template placed far off the optical axis (a
  car cut by the frame) is not distorted.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
from numba import njit, prange

from vehicle_pose.clock import timed
from vehicle_pose.geometry.camera import Camera, look_at_camera
from vehicle_pose.loss.edges import model_edges
from vehicle_pose.model.library import VehicleModel
from vehicle_pose.render.renderer import Renderer
from vehicle_pose.search.views import upright_axes

__all__ = ["TemplateGrid", "ViewTemplates", "Placements", "match", "turn_to"]

FloatArray = npt.NDArray[np.float64]
Box = tuple[float, float, float, float]

_SEED = 20261204  # the points kept of each template's edge pixels: the same for every build
_SHARE = 200  # templates placed between two calls of match's ``between`` (0.2-0.3 s on two cores)


@dataclass(frozen=True)
class TemplateGrid:
    """The views of the templates: every ``azimuth_step`` degrees all round (0 = the vehicle's
    front, 90 = its left side), each of ``elevations`` (degrees above the ground), each camera
    ``distance`` (bounding-sphere radii from the centre: 2.5 is a phone a metre or two from a
    car, 20 nearly orthographic); each keeps at most ``points`` edge points, drawn with the
    bounding sphere ``pixels`` pixels in radius. The faces drawn are the exterior of the level
    of ``faces``."""

    azimuth_step: float = 5.0
    elevations: tuple[float, ...] = (0.0, 8.0, 16.0, 24.0, 32.0)
    distances: tuple[float, ...] = (2.5, 4.0, 8.0, 20.0)
    points: int = 192
    pixels: float = 70.0
    faces: int = 8192

    def __post_init__(self) -> None:
        if not (0.5 <= self.azimuth_step <= 90.0) or not self.elevations or not self.distances:
            raise ValueError(f"unusable template grid {self}")
        if min(self.distances) <= 1.05 or self.points < 8 or self.pixels < 8:
            raise ValueError(f"unusable template grid {self}")

    @property
    def azimuths(self) -> tuple[float, ...]:
        return tuple(float(a) for a in np.arange(0.0, 360.0 - 1e-9, self.azimuth_step))

    def key(self) -> str:
        """A text naming the grid, for the prepared-model store."""
        return repr(sorted(asdict(self).items()))


def turn_to(ray: FloatArray) -> FloatArray:
    """The smallest rotation (3, 3) taking the optical axis (0, 0, 1) to the direction ``ray``."""
    r = np.asarray(ray, np.float64) / np.linalg.norm(ray)
    axis = np.cross([0.0, 0.0, 1.0], r)
    s = float(np.linalg.norm(axis))
    if s < 1e-12:
        return np.eye(3)
    angle = float(np.arctan2(s, r[2]))
    out: FloatArray = cv2.Rodrigues(axis / s * angle)[0]
    return out


@dataclass(frozen=True)
class ViewTemplates:
    """A model's edge templates (see the module docstring).

    Attributes
    ----------
    views : (T, 3) float64
        Azimuth and elevation (degrees) and camera distance (radii) of each template.
    rotations : (T, 3, 3) float64
        Model-to-camera rotation of each template's camera, its axis through the model's centre.
    points : (P, 2) float32
        Edge points of all templates, in normalised image coordinates about the centre's image.
    bins : (P,) int8
        Their orientation bins (:data:`~vehicle_pose.loss.edges.ORIENTATIONS`).
    offsets : (T + 1,) int64
        Template ``t``'s points are ``points[offsets[t]:offsets[t + 1]]``.
    boxes : (T, 4) float64
        The box of each template's projection (normalised coordinates, X0, Y0, X1, Y1).
    centre : (3,) float64, radius : float
        The model's bounding sphere (mesh units), about which the templates turn.
    """

    views: FloatArray
    rotations: FloatArray
    points: npt.NDArray[np.float32]
    bins: npt.NDArray[np.int8]
    offsets: npt.NDArray[np.int64]
    boxes: FloatArray
    centre: FloatArray
    radius: float

    def __len__(self) -> int:
        return int(self.views.shape[0])

    def camera(self, index: int, focal: float, u: float, v: float, principal: tuple[float, float],
               width: int, height: int) -> Camera:
        """The camera that shows template ``index`` scaled by ``focal`` (pixels) with the model's
        centre at pixel ``(u, v)``, for a ``width`` x ``height`` image whose principal point is
        ``principal``."""
        K = np.array([[focal, 0.0, principal[0]], [0.0, focal, principal[1]], [0.0, 0.0, 1.0]])
        ray = np.array([(u - principal[0]) / focal, (v - principal[1]) / focal, 1.0])
        ray /= np.linalg.norm(ray)
        R = turn_to(ray) @ self.rotations[index]
        depth = float(self.views[index, 2]) * self.radius
        return Camera(K, R, depth * ray - R @ self.centre, width, height)

    def arrays(self) -> dict[str, npt.NDArray[Any]]:
        """The arrays that make the templates (for the prepared-model store)."""
        return {"views": self.views, "rotations": self.rotations, "points": self.points, "bins": self.bins,
                "offsets": self.offsets, "boxes": self.boxes, "sphere": np.append(self.centre, self.radius)}

    @classmethod
    def from_arrays(cls, a: dict[str, npt.NDArray[Any]]) -> ViewTemplates:
        sphere = np.asarray(a["sphere"], np.float64)
        return cls(np.asarray(a["views"], np.float64), np.asarray(a["rotations"], np.float64),
                   np.asarray(a["points"], np.float32), np.asarray(a["bins"], np.int8),
                   np.asarray(a["offsets"], np.int64), np.asarray(a["boxes"], np.float64), sphere[:3],
                   float(sphere[3]))

    @classmethod
    def build(cls, model: VehicleModel, renderer: Renderer, grid: TemplateGrid = TemplateGrid()) -> ViewTemplates:
        """Draw the templates of ``model`` over ``grid`` (about 3 s for 1440 views on two cores)."""
        mesh = model.exterior(grid.faces, renderer)
        centre, radius = model.mesh.sphere
        up, forward = upright_axes(model)
        samples = model.mesh.sample_points(600)
        rng = np.random.default_rng(_SEED)
        views, rotations, points, bins, boxes = [], [], [], [], []
        offsets = [0]
        for d in grid.distances:
            focal = grid.pixels * d
            half = int(np.ceil(focal * np.tan(np.arcsin(min(0.99, 1.0 / d))))) + 4
            size = 2 * half + 1
            for el in grid.elevations:
                for az in grid.azimuths:
                    cam = look_at_camera(centre, forward, up, azimuth_deg=az, elevation_deg=el, distance=d * radius,
                                         focal=focal, width=size, height=size)
                    frame = renderer.render(mesh, cam)
                    edges = model_edges(frame)
                    r, c = np.nonzero(edges >= 0)
                    b = edges[r, c]
                    if r.size > grid.points:
                        keep = np.sort(rng.choice(r.size, grid.points, replace=False))
                        r, c, b = r[keep], c[keep], b[keep]
                    points.append(np.stack([(c + frame.x0 - half) / focal, (r + frame.y0 - half) / focal], axis=1))
                    bins.append(b)
                    offsets.append(offsets[-1] + r.size)
                    q = (cam.project(samples) - half) / focal
                    boxes.append([q[:, 0].min(), q[:, 1].min(), q[:, 0].max(), q[:, 1].max()])
                    views.append([az, el, d])
                    rotations.append(cam.R)
        return cls(np.array(views, np.float64), np.array(rotations, np.float64),
                   np.concatenate(points).astype(np.float32), np.concatenate(bins).astype(np.int8),
                   np.array(offsets, np.int64), np.array(boxes, np.float64), np.asarray(centre, np.float64),
                   float(radius))


@dataclass(frozen=True)
class Placements:
    """The best placement of each (template, box) pair tried: ``cost`` (T, B), inf where none
    was tried, and ``focal``, ``u``, ``v`` (T, B), the scale (pixels) and the image of the
    model's centre."""

    cost: FloatArray
    focal: FloatArray
    u: FloatArray
    v: FloatArray


@njit(cache=True, nogil=True)
def _turn(ray_x: float, ray_y: float) -> Any:  # pragma: no cover - compiled
    """:func:`turn_to` of the ray ``(ray_x, ray_y, 1)``, its nine entries row by row (a tuple:
    a placement allocates nothing)."""
    n = np.sqrt(ray_x * ray_x + ray_y * ray_y + 1.0)
    rx, ry, rz = ray_x / n, ray_y / n, 1.0 / n
    s = np.sqrt(rx * rx + ry * ry)
    if s < 1e-12:
        return 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0
    kx, ky = -ry / s, rx / s
    c = rz
    # Rodrigues' formula about the axis (kx, ky, 0) by the angle whose sine is s, cosine rz.
    return (c + kx * kx * (1.0 - c), kx * ky * (1.0 - c), ky * s,
            kx * ky * (1.0 - c), c + ky * ky * (1.0 - c), -kx * s,
            -ky * s, kx * s, c)


@njit(cache=True, nogil=True)
def _score(xs: Any, ys: Any, planes: Any, first: int, last: int, costs: Any, H: int, W: int, f: float, u: float,
           v: float, cx: float, cy: float, min_seen: float, at: Any) -> float:  # pragma: no cover - compiled
    """The mean cost of a template's points placed at focal length ``f`` with the centre's image
    at ``(u, v)``, over those inside the frame; inf when fewer than ``min_seen`` are. The points
    are ``(xs, ys)`` (normalised coordinates), ``planes`` each one's orientation bin times
    ``H * W``: its costs' offset in ``costs``, the ``H`` x ``W`` maps of every bin end to end.
    ``at`` is scratch space for ``last - first`` indices."""
    # The placed camera turns the template's axis onto the ray through (u, v): each point's ray
    # turns with it (exact, off the axis too).
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = _turn((u - cx) / f, (v - cy) / f)
    # First every point's cost index (-1 outside the frame or behind the camera), a loop without
    # branches that the compiler runs several points at a time; then the costs summed in order.
    n = last - first
    for i in range(n):
        px, py = xs[first + i], ys[first + i]
        dz = r20 * px + r21 * py + r22
        ahead = dz > 1e-6
        dz = max(dz, 1e-6)
        x = np.floor(cx + f * (r00 * px + r01 * py + r02) / dz + 0.5)
        y = np.floor(cy + f * (r10 * px + r11 * py + r12) / dz + 0.5)
        inside = ahead and x >= 0.0 and y >= 0.0 and x < W and y < H
        at[i] = planes[first + i] + int(y) * W + int(x) if inside else -1
    acc = 0.0
    seen = 0
    for i in range(n):
        if at[i] >= 0:
            acc += costs[at[i]]
            seen += 1
    if seen == 0 or seen < min_seen * n:
        return np.inf
    return acc / seen


@njit(cache=True, nogil=True)
def _keep(best: Any, where: Any, t: int, k: int, c: float, f: float, u: float, v: float
          ) -> bool:  # pragma: no cover - compiled
    """Keeps placement (f, u, v) of template ``t`` about target ``k`` where its cost ``c`` is the
    lowest so far."""
    if c < best[t, k]:
        best[t, k] = c
        where[t, k, 0] = f
        where[t, k, 1] = u
        where[t, k, 2] = v
        return True
    return False

@njit(cache=True, parallel=True)
def _match(xs: Any, ys: Any, planes: Any, offsets: Any, boxes: Any, allowed: Any, costs: Any, H: int, W: int,
           min_seen: float, targets: Any, scales: Any, step: float, min_iou: float, cx: float, cy: float,
           stride: float) -> tuple[Any, Any]:  # pragma: no cover
    T = offsets.size - 1
    B = targets.shape[0]
    best = np.full((T, B), np.inf)
    where = np.zeros((T, B, 3))
    for t in prange(T):
        if not allowed[t]:
            continue
        bx0, by0, bx1, by1 = boxes[t, 0], boxes[t, 1], boxes[t, 2], boxes[t, 3]
        first, last = offsets[t], offsets[t + 1]
        if last == first:
            continue
        at = np.empty(last - first, np.int64)
        for k in range(B):
            tx0, ty0, tx1, ty1 = targets[k, 0], targets[k, 1], targets[k, 2], targets[k, 3]
            t_area = max(tx1 - tx0, 1.0) * max(ty1 - ty0, 1.0)
            base = np.sqrt(max(tx1 - tx0, 1.0) / (bx1 - bx0) * max(ty1 - ty0, 1.0) / (by1 - by0))
            fine = 0.0
            for si in range(scales.size):
                f = base * scales[si]
                bw, bh = f * (bx1 - bx0), f * (by1 - by0)
                st = max(1.0, step * max(bw, bh))
                coarse = stride * st
                # The centre's image u is such that the template's box [u + f bx0, u + f bx1]
                # overlaps the target by at least min_iou of the target's width (an IoU of
                # min_iou needs that much), and the same for v; every other step in between
                # (the best of them is searched again on the full step below).
                mw, mh = min_iou * (tx1 - tx0), min_iou * (ty1 - ty0)
                u_lo, u_hi = tx0 + mw - f * bx1, tx1 - mw - f * bx0
                v_lo, v_hi = ty0 + mh - f * by1, ty1 - mh - f * by0
                if u_hi < u_lo or v_hi < v_lo:
                    continue
                nu = int((u_hi - u_lo) / coarse) + 1
                nv = int((v_hi - v_lo) / coarse) + 1
                for iu in range(nu):
                    u = u_lo + iu * coarse
                    cx0, cx1 = max(0.0, u + f * bx0), min(W - 1.0, u + f * bx1)
                    if cx1 <= cx0:
                        continue
                    for iv in range(nv):
                        v = v_lo + iv * coarse
                        cy0, cy1 = max(0.0, v + f * by0), min(H - 1.0, v + f * by1)
                        if cy1 <= cy0:
                            continue
                        iw = min(cx1, tx1) - max(cx0, tx0)
                        ih = min(cy1, ty1) - max(cy0, ty0)
                        if iw <= 0 or ih <= 0:
                            continue
                        inter = iw * ih
                        if inter / ((cx1 - cx0) * (cy1 - cy0) + t_area - inter) < min_iou:
                            continue
                        if _keep(best, where, t, k, _score(xs, ys, planes, first, last, costs, H, W, f, u, v,
                                                           cx, cy, min_seen, at), f, u, v):
                            fine = st
            if not np.isfinite(best[t, k]):
                continue
            # About the best placement: one step of the position either way (with a stride of
            # one, the places between those tried), and the scale a half step either way.
            f0, u0, v0 = where[t, k, 0], where[t, k, 1], where[t, k, 2]
            half = np.sqrt(scales[1] / scales[0]) if scales.size > 1 else 1.0
            for fs in (1.0 / half, 1.0, half):
                for du in (-1.0, 0.0, 1.0):
                    for dv in (-1.0, 0.0, 1.0):
                        if fs == 1.0 and du == 0.0 and dv == 0.0:
                            continue
                        f, u, v = f0 * fs, u0 + du * fine, v0 + dv * fine
                        _keep(best, where, t, k, _score(xs, ys, planes, first, last, costs, H, W, f, u, v, cx, cy,
                                                 min_seen, at), f, u, v)
    return best, where


@timed("matching")
def match(templates: ViewTemplates, distance: npt.NDArray[np.float32], tau: float, targets: list[Box], *,
          allowed: npt.NDArray[np.bool_] | None = None, scales: tuple[float, float] = (0.8, 2.0),
          scale_step: float = 1.1, step: float = 0.04, min_iou: float = 0.6, min_seen: float = 0.5,
          principal: tuple[float, float] | None = None, stride: int = 1,
          between: Callable[[], None] | None = None) -> Placements:
    """Every allowed template's best placement about each target box.

    Parameters
    ----------
    templates : ViewTemplates
    distance : (ORIENTATIONS, H, W) float32
        The photo's directional distance transforms (:class:`~vehicle_pose.loss.edges.PhotoEdges`).
    tau : float
        Truncation of the distances (pixels).
    targets : list of (X0, Y0, X1, Y1)
        Boxes in the photo's pixels about which the templates are placed.
    allowed : (T,) bool, keyword-only
        The templates to try (all by default).
    scales : (low, high), keyword-only
        The scales tried, as factors of the one that fits the template's box to the target's
        (a car cut by the frame projects larger than its box), every ``scale_step``.
    step : float, keyword-only
        The position step, a fraction of the placed template's larger side.
    min_iou : float, keyword-only
        The least IoU of the placed projection, cut to the frame, with the target box.
    min_seen : float, keyword-only
        The least share of a template's points inside the frame: a placement is scored on its
        points inside only (beyond the frame nothing is known), and one with less than this
        share in view is not tried.
    principal : (cx, cy), keyword-only
        The photo's principal point (pixels); the image centre by default.
    stride : int, keyword-only
        The positions are first tried every ``stride`` steps, then the best of them again
        one step either way (1: every step).
    between : callable, keyword-only
        Called after each share of a target's placements (the targets are placed one at a
        time, each :data:`_SHARE` templates at a time): a caller's deadline can stop the match
        within a fraction of a second.
    """
    if not targets:
        raise ValueError("matching needs at least one target box")
    costs = (np.minimum(distance, np.float32(tau)) / np.float32(tau)).astype(np.float32).ravel()
    count = int(np.floor(np.log(scales[1] / scales[0]) / np.log(scale_step) + 1e-9)) + 1
    factors = scales[0] * scale_step ** np.arange(count)
    mask = np.ones(len(templates), np.bool_) if allowed is None else np.asarray(allowed, np.bool_)
    _, H, W = distance.shape
    cx, cy = principal if principal is not None else (0.5 * (W - 1), 0.5 * (H - 1))
    boxes = np.asarray(targets, np.float64)
    xs = templates.points[:, 0].astype(np.float64)
    ys = templates.points[:, 1].astype(np.float64)
    planes = templates.bins.astype(np.int64) * (H * W)
    chosen = np.flatnonzero(mask)
    # With a caller to hear between, each target's templates are placed a share at a time (every
    # template is placed on its own, so the placements are the same): a share is every n-th
    # template, spread over the whole range so that the parallel loop's threads share it evenly.
    n = 1 if between is None else max(1, -(-chosen.size // _SHARE))
    best = np.full((len(templates), len(boxes)), np.inf)
    where = np.zeros((len(templates), len(boxes), 3))
    for k in range(len(boxes)):  # each target on its own: the same placements as all at once
        for i in range(n):
            share = chosen[i::n]
            part = np.zeros_like(mask)
            part[share] = True
            b, w = _match(xs, ys, planes, templates.offsets, templates.boxes, part, costs, H, W,
                          float(min_seen), boxes[k:k + 1], factors, float(step),
                          float(min_iou), float(cx), float(cy), float(stride))
            best[share, k], where[share, k] = b[share, 0], w[share, 0]
            if between is not None:
                between()
    return Placements(best, where[..., 0], where[..., 1], where[..., 2])
