"""Start poses for the optimiser (method.md §5, step 1) when the client gives no start camera.

A grid of views (azimuth x elevation x in-plane roll) is placed so that the model's projection
fills the vehicle's region, rendered at low resolution and scored against the region (silhouette
IoU) and the photo (the invariant loss on the region's pixels); the best few distinct views are
kept. Start poses from matched wheel ellipses (:mod:`vehicle_pose.search.wheels`) are scored the same
way, so both kinds compete on one scale.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from vehicle_pose.errors import CameraError
from vehicle_pose.geometry.camera import Camera, look_at_camera, to_pixels
from vehicle_pose.geometry.window import Window
from vehicle_pose.loss.alternatives import SilhouetteIoULoss
from vehicle_pose.loss.invariant import InvariantLoss, make_target
from vehicle_pose.metrics import rotation_error
from vehicle_pose.model.library import VehicleModel
from vehicle_pose.model.parts import model_frame
from vehicle_pose.registration.options import WINDOW_MARGIN
from vehicle_pose.render.renderer import Renderer
from vehicle_pose.segment.region import VehicleRegion

__all__ = [
    "Box",
    "box_union",
    "Candidate",
    "SearchGrid",
    "parse_bbox",
    "fit_to_box",
    "box_overflow",
    "upright_axes",
    "view_camera",
    "refocus",
    "score_cameras",
    "view_search",
    "distinct",
    "WINDOW_MARGIN",
]

Box = tuple[float, float, float, float]
FloatArray = npt.NDArray[np.float64]


def parse_bbox(value: str | Sequence[float], width: int, height: int) -> Box:
    """A box ``X0,Y0,X1,Y1`` (pixels) checked against the image; CameraError if unusable."""
    try:
        parts = [float(v) for v in (value.split(",") if isinstance(value, str) else value)]
    except (TypeError, ValueError):
        raise CameraError(f"bbox {value!r} must be four numbers X0,Y0,X1,Y1") from None
    if len(parts) != 4 or not all(np.isfinite(parts)):
        raise CameraError(f"bbox {value!r} must be four finite numbers X0,Y0,X1,Y1")
    x0, y0, x1, y1 = parts
    x0, x1 = max(x0, 0.0), min(x1, width - 1.0)
    y0, y1 = max(y0, 0.0), min(y1, height - 1.0)
    if x1 - x0 < 8 or y1 - y0 < 8:
        raise CameraError(f"bbox {value!r} covers too little of the {width}x{height} photo")
    return x0, y0, x1, y1


@dataclass(frozen=True)
class Candidate:
    """A scored start pose.

    ``score`` = (1 - ``iou``) + ``loss`` / its maximum: lower is better. ``source`` is
    ``"view-search"`` or ``"wheels"``; ``detail`` says which view or which wheel pair.
    """

    camera: Camera
    source: str
    score: float = float("inf")
    iou: float = 0.0
    loss: float = float("inf")
    detail: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict[str, object]:
        return {"source": self.source, "score": self.score, "iou": self.iou, "loss": self.loss, **self.detail}


@dataclass(frozen=True)
class SearchGrid:
    """The views of the search: degrees, azimuth 0 = the vehicle's front, 90 = its left side."""

    azimuths: tuple[float, ...] = tuple(float(a) for a in range(0, 360, 15))
    elevations: tuple[float, ...] = (4.0, 16.0, 30.0)
    rolls: tuple[float, ...] = (-6.0, 0.0, 6.0)
    focal: float = 1.5
    """Focal length of the search views, in image widths (about a 50 mm lens on full frame)."""


def fit_to_box(camera: Camera, points: FloatArray, anchor: FloatArray, box: Box, *, rounds: int = 3,
               clip: bool = False) -> Camera:
    """The camera moved along and across its axis so that ``points`` project onto ``box``.

    The rotation and intrinsics stay; ``anchor`` (a point of the model, its centre) keeps its
    direction while the depth is scaled to match the box's size and the image shifted to match
    its centre. With ``clip`` the projection is cut to the image before it is compared with
    the box, so a box that a photo's border cuts (a vehicle partly out of the frame) is matched
    by a projection cut the same way rather than shrunk into the photo.
    """
    K, R = camera.K, camera.R
    bw, bh = max(box[2] - box[0], 1.0), max(box[3] - box[1], 1.0)
    bc = np.array([0.5 * (box[0] + box[2]), 0.5 * (box[1] + box[3])])
    depth = float(camera.to_camera(anchor[None])[0, 2])
    pix = camera.project(anchor[None])[0]
    if not (depth > 0 and np.all(np.isfinite(pix))):
        depth, pix = float(np.linalg.norm(camera.t)), camera.centre
    # Each round projects the points as Camera.project would, without making a camera: the
    # rotation stays, so the points are turned once (the anchored search calls this for every
    # sample, and the cameras cost more than the arithmetic).
    turned = np.asarray(points, dtype=np.float64) @ R.T
    pivot = R @ anchor
    for _ in range(rounds):
        ray = np.linalg.solve(K, np.array([pix[0], pix[1], 1.0]))
        t = depth * ray - pivot
        if not np.all(np.isfinite(t)):
            raise CameraError("camera holds non-finite numbers")
        uv = to_pixels(turned + t, K)
        if not np.all(np.isfinite(uv)):
            depth *= 2.0
            continue
        lo, hi = uv.min(0), uv.max(0)
        if clip:
            size = np.array([camera.width - 1.0, camera.height - 1.0])
            lo, hi = np.clip(lo, 0.0, size), np.clip(hi, 0.0, size)
        span = hi - lo
        depth *= float(np.sqrt(max(span[0], 1e-6) / bw * max(span[1], 1e-6) / bh))
        pix = pix + bc - 0.5 * (lo + hi)
    ray = np.linalg.solve(K, np.array([pix[0], pix[1], 1.0]))
    return Camera(K, R, depth * ray - pivot, camera.width, camera.height)


def turned_away(camera: Camera, start: Camera, spread: float) -> float:
    """How far ``camera`` is turned from the start camera's rotation, squared in units of
    ``spread`` degrees (the start's expected rotation error): a start camera is evidence about
    the pose as the photo is, and the searches from it weigh the two
    (docs/decisions/0039-start-prior.md)."""
    return (rotation_error(camera.R, start.R) / spread) ** 2


def box_union(a: Box, b: Box | None) -> Box:
    """The smallest box holding both (``a`` when ``b`` is None)."""
    if b is None:
        return a
    return min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3])


def box_overflow(camera: Camera, points: FloatArray, box: Box, margin: float, shortfall: float | None = None) -> float:
    """How far ``points`` project beyond ``box`` grown by ``margin`` of its size on each side,
    summed over the four sides in units of the box's width or height (0 inside).

    A side of the box on the photo's border says nothing (the vehicle may go on beyond the
    frame) and is not checked; points behind the camera count as far out. Falling short of
    the box counts only with ``shortfall``, beyond that fraction of its size: a box drawn by
    hand is often loose, and a two-sided term with the same tolerance cost accuracy on the real
    and the photoreal cases (docs/decisions/0006-real-photo-terms.md).
    """
    uv = camera.project(points)
    if not np.all(np.isfinite(uv)):
        return 4.0
    bw, bh = max(box[2] - box[0], 1.0), max(box[3] - box[1], 1.0)
    lo, hi = uv.min(0), uv.max(0)
    out = 0.0
    if box[0] > 1.0:
        out += max(0.0, box[0] - margin * bw - lo[0]) / bw
    if box[2] < camera.width - 2.0:
        out += max(0.0, hi[0] - box[2] - margin * bw) / bw
    if box[1] > 1.0:
        out += max(0.0, box[1] - margin * bh - lo[1]) / bh
    if box[3] < camera.height - 2.0:
        out += max(0.0, hi[1] - box[3] - margin * bh) / bh
    if shortfall is not None:
        sx, sy = shortfall * bw, shortfall * bh
        out += (max(0.0, lo[0] - box[0] - sx) + max(0.0, box[2] - sx - hi[0])) / bw
        out += (max(0.0, lo[1] - box[1] - sy) + max(0.0, box[3] - sy - hi[1])) / bh
    return float(out)


def upright_axes(model: VehicleModel) -> tuple[FloatArray, FloatArray]:
    """The model's up axis and its forward direction (rear axle to front, in the ground plane),
    unit vectors in mesh coordinates: what azimuth and elevation are measured from."""
    axes = model_frame(model.info.up, model.wheels).axes
    return axes[2], axes[0]


def view_camera(
    model: VehicleModel, azimuth: float, elevation: float, roll: float, box: Box, width: int, height: int, focal: float
) -> Camera:
    """A camera at the given view (degrees) whose projection of the model fills ``box``."""
    centre, radius = model.mesh.sphere
    up, fwd = upright_axes(model)
    cam = look_at_camera(centre, fwd, up, azimuth_deg=azimuth, elevation_deg=elevation,
                         distance=4.0 * radius, focal=focal, width=width, height=height)
    if roll:
        R = Rotation.from_euler("z", roll, degrees=True).as_matrix() @ cam.R
        cam = Camera(cam.K, R, R @ (cam.R.T @ cam.t), width, height)
    return fit_to_box(cam, model.mesh.extreme_points(600), centre, box)


def refocus(camera: Camera, focal: float, model: VehicleModel, box: Box) -> Camera:
    """The camera with focal length ``focal`` (pixels), moved so the model still fills ``box``."""
    K = camera.K.copy()
    K[0, 0] *= focal / camera.K[0, 0]
    K[1, 1] *= focal / camera.K[1, 1]
    cam = Camera(K, camera.R, camera.t, camera.width, camera.height)
    return fit_to_box(cam, model.mesh.extreme_points(600), model.mesh.sphere[0], box)


class _Scorer:
    """Scores cameras on a reduced photo against a region: silhouette IoU and invariant loss.

    With a ``margin``, the scores are taken on a window around the region's box (grown by
    ``margin`` times its longer side) rather than on the whole photo, reduced to ``size``.
    """

    def __init__(self, rgb: npt.NDArray[np.uint8], region: VehicleRegion, model: VehicleModel,
                 renderer: Renderer, size: int, max_faces: int, margin: float | None) -> None:
        H, W = rgb.shape[:2]
        self.window = Window.around(region.box, W, H, size=size, margin=margin)
        target = make_target(self.window.image(rgb), self.window.mask(region.mask), color=False)
        self.loss = InvariantLoss(target)
        self.miss = SilhouetteIoULoss(target)
        self.mesh = model.exterior(max_faces, renderer)
        self.renderer = renderer

    def __call__(self, camera: Camera) -> tuple[float, float, float]:
        frame = self.renderer.render(self.mesh, self.window.camera(camera))
        iou = 1.0 - self.miss(frame)
        loss = float(self.loss(frame))
        return (1.0 - iou) + loss / self.loss.max_value(5), iou, loss


def score_cameras(
    rgb: npt.NDArray[np.uint8],
    region: VehicleRegion,
    model: VehicleModel,
    candidates: Iterable[Candidate],
    renderer: Renderer,
    *,
    size: int = 160,
    max_faces: int = 4096,
    margin: float | None = WINDOW_MARGIN,
) -> list[Candidate]:
    """The candidates with their score, IoU and loss filled in, best first.

    They are scored on a window around the region (see :class:`~vehicle_pose.geometry.window.Window`)
    reduced to ``size`` pixels; ``margin=None`` scores on the whole photo.
    """
    scorer = _Scorer(rgb, region, model, renderer, size, max_faces, margin)
    out = []
    for cand in candidates:
        score, iou, loss = scorer(cand.camera)
        out.append(replace(cand, score=score, iou=iou, loss=loss))
    return sorted(out, key=lambda c: c.score)


DISTINCT_ANGLE = 25.0
"""Degrees apart at which :func:`distinct` takes two views for two poses."""


def distinct(candidates: Sequence[Candidate], count: int, *, min_angle: float = DISTINCT_ANGLE) -> list[Candidate]:
    """The best ``count`` candidates whose rotations differ pairwise by at least ``min_angle``."""
    kept: list[Candidate] = []
    for cand in sorted(candidates, key=lambda c: c.score):
        if all(rotation_error(cand.camera.R, k.camera.R) >= min_angle for k in kept):
            kept.append(cand)
            if len(kept) == count:
                break
    return kept


def view_search(
    rgb: npt.NDArray[np.uint8],
    region: VehicleRegion,
    model: VehicleModel,
    renderer: Renderer,
    *,
    grid: SearchGrid = SearchGrid(),
    size: int = 160,
    max_faces: int = 4096,
    margin: float | None = WINDOW_MARGIN,
) -> list[Candidate]:
    """Every view of ``grid`` fitted to the region and scored (see :func:`score_cameras`), best
    first (cameras at the photo's size)."""
    H, W = rgb.shape[:2]
    cands = [
        Candidate(view_camera(model, az, el, roll, region.box, W, H, grid.focal * W), "view-search",
                  detail={"azimuth": az, "elevation": el, "roll": roll})
        for az in grid.azimuths
        for el in grid.elevations
        for roll in grid.rolls
    ]
    return score_cameras(rgb, region, model, cands, renderer, size=size, max_faces=max_faces, margin=margin)
