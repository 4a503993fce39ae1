"""The view-sphere search: the pose found on the photo's edges from every view, narrowed by the hints
(``docs/decisions/0020-view-sphere-search.md``).

1. **Targets**: the boxes the vehicle is looked for in. The client's box; else, with a start
   camera, the box of its projection grown to the vehicle's region GrabCut finds about it, and
   the photo's frame (a claims photo is mostly the car);
   else the frame and the regions GrabCut finds.
2. **Hypotheses** (:func:`~vehicle_pose.search.templates.match`): every template of the model's
   view sphere allowed by the start camera (all of them without one) placed about each target
   at the scales and positions where its projection, cut to the frame, covers the target; the
   best placement of each template by the directional chamfer.
3. **Ranking**: the best ``sphere_rank`` placements of each target rendered and scored by the
   two-way chamfer (:class:`~vehicle_pose.loss.edges.TwoWayChamfer`) over the targets' union;
   the one-way chamfer alone prefers the half-turn twin of most real photos.
4. **Refinement**: the best ``sphere_refine`` ranked poses at least ``sphere_apart`` degrees
   apart, each refined on the same cost in all seven view coordinates (with the client's box,
   plus the cost of leaving it).
5. **Choice**: the refined pose of lowest cost; its margin over the best pose at least
   :data:`RIVAL_APART` degrees away and its lead over the typical placed template say how
   credible it is. Where the shading explains the photo, the shading fit polishes the pose it
   explains best and judges it against its best rival; else the edges decide, the best pose
   weighed against its half-turn twin refined, and the search's sizes vote (:func:`sphere_pose`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from vehicle_pose.clock import timed
from vehicle_pose.errors import CameraError, PoseError
from vehicle_pose.geometry.camera import Camera
from vehicle_pose.geometry.parametrize import ViewParams
from vehicle_pose.loss.edges import PhotoEdges, TwoWayChamfer, photo_edges
from vehicle_pose.metrics import rotation_error
from vehicle_pose.model.library import VehicleModel
from vehicle_pose.model.metadata import parse_axis
from vehicle_pose.photo import resized
from vehicle_pose.registration.deadline import Deadline
from vehicle_pose.registration.fit import Fit, FitPlan, Progress, fit
from vehicle_pose.registration.options import RegistrationOptions
from vehicle_pose.registration.result import LevelReport
from vehicle_pose.registration.segmentation import box_mask, resegment, silhouette
from vehicle_pose.registration.structure import loss_at, losses_at
from vehicle_pose.render.renderer import Frame, Renderer
from vehicle_pose.search.optimize import Optimizer
from vehicle_pose.search.templates import ViewTemplates, match, turn_to
from vehicle_pose.search.views import Box, box_overflow, box_union, turned_away
from vehicle_pose.segment.grabcut import grabcut_foreground
from vehicle_pose.segment.region import VehicleRegion, find_vehicle, largest_component

__all__ = ["Pose", "SphereSearch", "sphere_search", "half_turn", "sphere_fit", "sphere_pose", "edge_evidence",
           "RIVAL_APART"]

RIVAL_APART = 15.0
"""Degrees apart at which two refined poses are two poses rather than one found twice."""

_INVALID = 10.0  # the cost of coordinates that give no camera

REGION_BORDERS: tuple[tuple[float, float], ...] = ((0.08, 0.1), (0.18, 0.2), (0.28, 0.3))
"""GrabCut rectangles of the regions searched without a hint (fractions of W, H inside the border)."""


@dataclass
class Pose:
    """One hypothesis: its camera (at the working size), the template it came from, its target
    box's index, its cost when ranked and, once refined, its refined cost and evaluations."""

    camera: Camera
    template: int
    target: int
    ranked: float
    cost: float = float("inf")
    evaluations: int = 0
    detail: dict[str, float] = field(default_factory=dict)


@dataclass
class SphereSearch:
    """The refined poses (best first), the ranked ones, the targets, the time spent, the checks,
    the templates searched and the cost each target's poses were scored by."""

    refined: list[Pose]
    ranked: list[Pose]
    targets: list[Target]
    seconds: float
    checks: dict[str, float]
    templates: ViewTemplates
    costs: list[_Cost] = field(default_factory=list)

    @property
    def best(self) -> Pose:
        return self.refined[0]

    def listed(self) -> list[dict[str, Any]]:
        """The refined hypotheses as the result reports them."""
        out = []
        for p in self.refined:
            az, el, d = self.templates.views[p.template] if p.template >= 0 else (np.nan, np.nan, np.nan)
            source = "start" if p.template < 0 else "half-turn twin" if p.detail.get("twin") else "view-sphere"
            out.append({"source": source, "azimuth": float(az),
                        "elevation": float(el), "distance": float(d),
                        "target": list(self.targets[p.target].box), "ranked": p.ranked, "cost": p.cost,
                        "evaluations": p.evaluations})
        return out


class _Cost:
    """The two-way chamfer of the model's exterior at a camera for the working photo, scored at
    the search size over the target box ``region`` (the photo's ``edges``, found once for every
    target; its edges outside ``region`` but inside ``among`` cost ``clutter`` each), plus the
    box term with a client's box, and with a ``start`` camera the start's prior
    (``terms.start_weight`` over the share of the model the start shows inside the frame:
    docs/decisions/0039-start-prior.md, 0050-a-cut-start-weighs-more.md)."""

    def __init__(self, image: npt.NDArray[np.uint8], model: VehicleModel, region: Box, box: Box | None,
                 options: RegistrationOptions, renderer: Renderer, edges: PhotoEdges, among: Box,
                 clutter: float, start: Camera | None = None) -> None:
        st = options.structure
        self.chamfer = TwoWayChamfer(image, region=region, tau=st.anchor_tau, crease=options.terms.edge_crease,
                                     edges=edges, among=among, clutter=clutter)
        self.size = (image.shape[1], image.shape[0])
        self.mesh = model.exterior(options.pyramid.min_faces, renderer)
        self.renderer = renderer
        self.box, self.points = box, model.mesh.extreme_points(1000)
        self.terms, self.start, self.spread = options.terms, start, options.structure.structure_spread
        # The chamfer is a mean over the edges in view: a start that shows part of the car
        # (the rest beyond the frame) leaves the edges less evidence, and its prior weighs more,
        # by the share of the model's points it shows inside the frame.
        self.prior = 0.0 if start is None else options.terms.start_weight / max(_in_frame(model, start), 0.05)
        self.count = 0

    def __call__(self, camera: Camera) -> float:
        cam = camera.scaled(*self.size)
        return self._priced(cam, self.renderer.render(self.mesh, cam))

    def many(self, cameras: list[Camera]) -> list[float]:
        """The cost of each camera, as :meth:`__call__` gives it, their frames drawn together
        (:meth:`~vehicle_pose.render.renderer.Renderer.render_many`, each frame the same)."""
        cams = [camera.scaled(*self.size) for camera in cameras]
        return [self._priced(cam, frame) for cam, frame in zip(cams, self.renderer.render_many(self.mesh, cams),
                                                                strict=True)]

    def _priced(self, cam: Camera, frame: Frame) -> float:
        """The cost of ``cam`` (at the search size) whose frame is ``frame``."""
        self.count += 1
        value = self.chamfer(frame)
        if self.box is not None and self.terms.box_weight > 0:
            value += self.terms.box_weight * box_overflow(cam, self.points, self.box, self.terms.box_tolerance,
                                                          self.terms.box_shortfall)
        if self.start is not None and self.prior > 0:
            value += self.prior * turned_away(cam, self.start, self.spread)
        return value


def _in_frame(model: VehicleModel, camera: Camera) -> float:
    """The share of the model's points (2000 of its vertices, drawn at random) that ``camera``
    shows inside its frame; points behind the camera are not shown."""
    uv = camera.project(model.mesh.sample_points(2000))  # nan behind the camera: never inside
    inside = (uv[:, 0] >= 0) & (uv[:, 0] <= camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] <= camera.height)
    return float(inside.mean())


def _search_size(work: npt.NDArray[np.uint8], options: RegistrationOptions) -> tuple[int, int]:
    """The size the search scores at: the working photo reduced to ``sphere_size`` pixels on its
    longer side (never enlarged)."""
    Hf, Wf = work.shape[:2]
    s = min(1.0, options.search.sphere_size / max(Wf, Hf))
    return max(8, round(Wf * s)), max(8, round(Hf * s))


@dataclass(frozen=True)
class Target:
    """A box the vehicle is looked for in (working-photo pixels) and the vehicle's pixels as
    segmented there (H, W) bool, on which the shading is checked."""

    box: Box
    mask: npt.NDArray[np.bool_]


def _targets(work: npt.NDArray[np.uint8], model: VehicleModel, init: Camera | None, box: Box | None,
             between: Callable[[], None] | None = None, about: _About | None = None) -> list[Target]:
    """The boxes the vehicle is looked for in: the client's box (the vehicle segmented in it by
    GrabCut); else the photo's frame (a claims photo is mostly the car), with a start camera the
    box of its projection first (grown to the vehicle's region about it with ``about``);
    without a hint, the frame and the regions GrabCut finds from rectangles 8-30 % inside the
    border (one box each, those that differ). ``between`` is called before the GrabCuts.

    A start camera says where the vehicle is: the regions GrabCut finds without it are not
    searched (one that holds a lamp or a panel can win, the model shrunk onto it, by a margin
    of a few thousandths of the cost; docs/decisions/0040-a-start-says-where.md)."""
    H, W = work.shape[:2]
    if box is not None:
        return [Target(box, find_vehicle(work, rect=box).mask)]
    out = [Target(_frame_box(work), np.ones((H, W), bool))]
    if init is not None:
        b = _seen_box(init, model, 4.0)
        if b is None:
            raise PoseError("the start pose puts the model out of the photo")
        if about is not None:
            b = box_union(b, _region_about(work, silhouette(model, init, about.renderer), about.margin))
        if _box_iou(b, out[0].box) < 0.8:
            out.insert(0, Target(b, find_vehicle(work, rect=b).mask))
        return out  # the start's box and the frame
    if between is not None:
        between()
    for region in _regions(work):
        if all(_box_iou(region.box, o.box) < 0.8 for o in out):
            out.append(Target(region.box, region.mask))
    return out


def _frame_box(work: npt.NDArray[np.uint8]) -> Box:
    """The box of the whole working photo: the frame's target."""
    H, W = work.shape[:2]
    return 0.0, 0.0, W - 1.0, H - 1.0


@dataclass(frozen=True)
class _About:
    """What finding the vehicle's region about a start camera needs: the renderer its
    silhouette is drawn with and GrabCut's seed margin (silhouette diagonals)."""

    renderer: Renderer
    margin: float


def _region_about(work: npt.NDArray[np.uint8], start: npt.NDArray[np.bool_], margin: float) -> Box:
    """The box of the vehicle's region about a start's silhouette ``start``: GrabCut seeded by
    the silhouette (:func:`~vehicle_pose.segment.grabcut.grabcut_foreground`, ``margin``), the
    rest of the photo but its one-pixel border probable background, so the region may reach as
    far as the vehicle's colours do (a start a little off or small shows part of the car); its
    largest piece. Where GrabCut keeps too little of the silhouette, the photo less its border
    (docs/decisions/0060-the-vehicle-s-region-about-the-start.md)."""
    open_ = np.ones(start.shape, bool)
    open_[[0, -1], :] = open_[:, [0, -1]] = False
    return VehicleRegion.from_mask(largest_component(grabcut_foreground(work, start, margin=margin,
                                                                        region=open_))).box


@timed("grabcut")
def _regions(work: npt.NDArray[np.uint8]) -> list[VehicleRegion]:
    """The regions GrabCut finds from the rectangles of :data:`REGION_BORDERS`. They are
    independent (each seeds its own thread's generator), and OpenCV lets go of the interpreter
    while it segments: they run side by side (charged to a running clock as one wait)."""
    with ThreadPoolExecutor(len(REGION_BORDERS), thread_name_prefix="region") as pool:
        return list(pool.map(lambda border: find_vehicle(work, border=border), REGION_BORDERS))


def _seen_box(camera: Camera, model: VehicleModel, least: float) -> Box | None:
    """The box of the model's projection cut to the frame; None where a point is behind the
    camera or the box is narrower or lower than ``least`` pixels."""
    uv = camera.project(model.mesh.extreme_points(600))
    if not np.all(np.isfinite(uv)):
        return None
    lo = np.clip(uv.min(0), 0, [camera.width - 1, camera.height - 1])
    hi = np.clip(uv.max(0), 0, [camera.width - 1, camera.height - 1])
    if hi[0] - lo[0] < least or hi[1] - lo[1] < least:
        return None
    return (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))


def _box_iou(a: Box, b: Box) -> float:
    iw = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    ih = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = iw * ih
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union if union > 0 else 0.0


def _allowed(templates: ViewTemplates, init: Camera | None, spread: float) -> npt.NDArray[np.bool_]:
    """The templates within ``spread`` degrees of the start's rotation (seen along its ray to the
    model's centre), every one without a start camera."""
    if init is None:
        return np.ones(len(templates), np.bool_)
    centre = init.to_camera(templates.centre[None])[0]
    R = turn_to(centre).T @ init.R  # the start as its template would show it, centre on the axis
    traces = np.einsum("tij,ij->t", templates.rotations, R)
    angles: npt.NDArray[np.float64] = np.degrees(np.arccos(np.clip((traces - 1.0) / 2.0, -1.0, 1.0)))
    return np.asarray(angles <= spread, np.bool_)


def _fit(pose: Pose, costs: list[_Cost], model: VehicleModel, options: RegistrationOptions, optimizer: Optimizer,
         free: tuple[int, ...], budget: int, focal_band: tuple[float, float] | None) -> Pose:
    """The pose refined in the view coordinates ``free`` (of seven) for ``budget`` evaluations,
    its focal length within ``focal_band`` (image widths) where one is given."""
    params = ViewParams(pose.camera, model.mesh.sphere[0], options.probes.dolly_pivot * model.mesh.sphere[1],
                        focal_band)
    index = np.array(free)
    cost = costs[pose.target]

    def fun(x: npt.NDArray[np.float64]) -> float:
        y = np.zeros(7)
        y[index] = x
        try:
            return cost(params.camera(y))
        except (PoseError, CameraError):
            return _INVALID

    res = optimizer(fun, np.zeros(len(free)), options.search.sphere_step * params.steps()[index],
                    max_evaluations=budget)
    y = np.zeros(7)
    y[index] = res.x
    if res.fun >= pose.cost:
        return Pose(pose.camera, pose.template, pose.target, pose.ranked, pose.cost,
                    pose.evaluations + res.evaluations, pose.detail)
    return Pose(params.camera(y), pose.template, pose.target, pose.ranked, float(res.fun),
                pose.evaluations + res.evaluations, pose.detail)


_HOLD = (3, 4, 5, 6)  # the view coordinates of place, size and focal length: the rotation held
_ALL = tuple(range(7))


def _refine(chosen: list[Pose], costs: list[_Cost], model: VehicleModel, options: RegistrationOptions,
            optimizer: Optimizer, progress: Progress | None, focal_band: tuple[float, float] | None) -> list[Pose]:
    """Successive halving: every chosen pose's place, size and focal length fitted with its
    rotation held (a template's placement is coarse, and a rotation refined with it would
    trade against it), then the better half refined in all seven coordinates, and again, until
    one is left; best first."""
    search = options.search
    pool = [_fit(p, costs, model, options, optimizer, _HOLD, search.sphere_hold, focal_band) for p in chosen]
    done: list[Pose] = []
    while pool:
        pool.sort(key=lambda p: p.cost)
        keep = max(1, len(pool) // 2)
        done += pool[keep:]
        pool = pool[:keep]
        if progress is not None:
            progress(f"view sphere: refining {len(pool)}", sum(c.count for c in costs), pool[0].cost)
        pool = [_fit(p, costs, model, options, optimizer, _ALL, search.sphere_evaluations, focal_band) for p in pool]
        if len(pool) == 1:
            done += pool
            break
    return sorted(done, key=lambda p: p.cost)


def _held(focal_band: tuple[float, float] | None) -> tuple[float, float] | None:
    """The focal lengths the search's placements and refinements keep within an EXIF's band:
    its geometric middle alone (``docs/decisions/0021-exif-focal.md``); None without a band."""
    if focal_band is None:
        return None
    lens = float(np.sqrt(focal_band[0] * focal_band[1]))
    return lens, lens


def half_turn(camera: Camera, model: VehicleModel) -> Camera:
    """The camera that sees the model turned half a turn about its up axis through its centre:
    the pose's front-back twin, whose outline is nearly the pose's own."""
    up = parse_axis(model.info.up)
    centre = model.mesh.sphere[0]
    turn = 2.0 * np.outer(up, up) - np.eye(3)
    R = camera.R @ turn
    return Camera(camera.K, R, camera.t + camera.R @ centre - R @ centre, camera.width, camera.height)


def _with_twin(searched: SphereSearch, model: VehicleModel, options: RegistrationOptions, optimizer: Optimizer,
               progress: Progress | None, focal_band: tuple[float, float] | None) -> SphereSearch:
    """The search with its best pose's half-turn twin refined as its poses were (place, size and
    focal length, then all seven coordinates) on the best pose's target, among its refined poses
    (kept first where it costs less), and its checks and time taken again.

    A car's outline half a turn away is nearly its own: the template matching places the twin's
    view where the pose's edges are, and its placements rank below the pose's neighbours, so
    the search may leave it unrefined. On real photos whose search ends on the twin of the right
    pose, the twin refines to the right pose at a lower cost
    (``docs/decisions/0037-half-turn-twin.md``)."""
    t0 = time.perf_counter()
    templates, best = searched.templates, searched.best
    camera = half_turn(best.camera, model)
    template = -1
    if best.template >= 0:
        az, el, d = templates.views[best.template]
        turned = np.mod(templates.views[:, 0] - az, 360.0) - 180.0  # 0 half a turn from the pose's azimuth
        template = int(np.argmin(np.abs(turned) + np.abs(templates.views[:, 1] - el)
                                 + np.abs(templates.views[:, 2] - d)))
    cost = searched.costs[best.target](camera)
    twin = Pose(camera, template, best.target, cost, cost, detail={"twin": 1.0})
    twin = _refine([twin], searched.costs, model, options, optimizer, progress, _held(focal_band))[0]
    refined = sorted([*searched.refined, twin], key=lambda p: p.cost)
    checks = searched.checks | _checks(refined, searched.ranked)
    return replace(searched, refined=refined, checks=checks, seconds=searched.seconds + time.perf_counter() - t0)


def sphere_search(
    work: npt.NDArray[np.uint8],
    model: VehicleModel,
    templates: ViewTemplates,
    options: RegistrationOptions,
    renderer: Renderer,
    optimizer: Optimizer,
    *,
    init: Camera | None = None,
    box: Box | None = None,
    progress: Progress | None = None,
    focal_band: tuple[float, float] | None = None,
    targets: list[Target] | None = None,
    only: int | None = None,
) -> SphereSearch:
    """The pose on the working photo ``work`` from the hints (the module docstring).

    ``init`` is a start camera and ``box`` the client's box, both for the working photo; a start
    narrows the views to ``sphere_spread`` degrees about it and prices every pose's turn from it
    (``terms.start_weight``).
    ``targets`` are those of an earlier search of the same photo and hints (found again
    without); ``only`` is the index of the one target searched (each target's by default; every
    target still prices its edges as clutter).
    ``focal_band`` (image widths, low and high; a lens known from the photo's EXIF) holds the
    focal length: each placed template is taken to the band's geometric middle by a dolly
    zoom (its size at the pivot kept) before it is ranked, and refined there (the edges do not
    tell focal lengths within a few per cent apart: a search within the band ends on its edge
    as often as not, docs/decisions/0021-exif-focal.md).
    """
    t0 = time.perf_counter()
    search = options.search
    Hf, Wf = work.shape[:2]
    tick = None if progress is None else lambda: progress("view sphere: finding the vehicle", 0, float("nan"))
    if tick is not None:
        tick()
    if targets is None:
        about = (_About(renderer, options.segmentation.grabcut_margin)
                 if init is not None and search.sphere_start_region else None)
        targets = _targets(work, model, init, box, tick, about)
    w, h = _search_size(work, options)
    sx, sy = w / Wf, h / Hf
    image = resized(work, w, h)
    small = [(t.box[0] * sx, t.box[1] * sy, t.box[2] * sx, t.box[3] * sy) for t in targets]
    client = None if box is None else small[0]
    union: Box = (min(b[0] for b in small), min(b[1] for b in small), max(b[2] for b in small),
                  max(b[3] for b in small))
    edges = photo_edges(image)
    costs = [_Cost(image, model, b, client, options, renderer, edges, union, search.sphere_clutter, init)
             for b in small]
    first = costs[0]
    if progress is not None:
        progress("view sphere: placing templates", 0, float("nan"))
    allowed = _allowed(templates, init, search.sphere_spread)
    sought = list(range(len(small))) if only is None else [only]
    placed = match(templates, first.chamfer.edges.distance, first.chamfer.tau, [small[k] for k in sought],
                   allowed=allowed, scales=search.sphere_scales, min_iou=search.sphere_iou, stride=search.sphere_stride,
                   between=None if progress is None else lambda: progress("view sphere: placing templates", 0,
                                                                          float("nan")))
    principal = (0.5 * (w - 1), 0.5 * (h - 1)) if init is None else tuple(init.scaled(w, h).K[:2, 2])
    pivot = options.probes.dolly_pivot * model.mesh.sphere[1]
    held = _held(focal_band)
    lens = None if held is None else held[0]
    ranked: list[Pose] = []
    for j, k in enumerate(sought):
        if progress is not None:
            progress(f"view sphere: ranking target {k + 1}/{len(small)}", len(ranked), float("nan"))
        order = np.argsort(placed.cost[:, j])[: search.sphere_rank]
        order = order[np.isfinite(placed.cost[order, j])]  # the unplaced (inf) sort last
        cams = []
        for t in order:
            cam = templates.camera(int(t), placed.focal[t, j], placed.u[t, j], placed.v[t, j], principal, w, h)
            full = cam.scaled(Wf, Hf)
            if lens is not None:
                full = ViewParams(full, model.mesh.sphere[0], pivot).dolly_zoom(lens * Wf / full.focal)
            cams.append(full)
        # The placements are one population: their frames are drawn together.
        for t, full, cost in zip(order, cams, costs[k].many(cams), strict=True):
            ranked.append(Pose(full, int(t), k, cost, detail={"placed": float(placed.cost[t, j])}))
    if init is not None:
        ranked.append(Pose(init, -1, 0, first(init), detail={"start": 1.0}))
    if not ranked:
        raise PoseError("no view of the model can be placed in the photo")
    ranked.sort(key=lambda p: p.ranked)
    refined = []
    for k in sought:
        chosen: list[Pose] = []
        for p in ranked:
            if p.target == k and all(rotation_error(p.camera.R, c.camera.R) >= search.sphere_apart for c in chosen):
                chosen.append(p)
            if len(chosen) == search.sphere_refine:
                break
        for p in chosen:
            p.cost = p.ranked
        if chosen:
            refined += _refine(chosen, costs, model, options, optimizer, progress, held)
    refined.sort(key=lambda p: p.cost)
    return SphereSearch(refined, ranked, targets, time.perf_counter() - t0, _checks(refined, ranked), templates,
                        list(costs))


def _checks(refined: list[Pose], ranked: list[Pose]) -> dict[str, float]:
    """The best refined pose's cost, its relative margin over the best pose at least
    :data:`RIVAL_APART` degrees away (refined, or else the first such ranked) and its lead over
    the typical ranked placement."""
    best = refined[0]
    rivals = [p.cost for p in refined[1:] if rotation_error(p.camera.R, best.camera.R) >= RIVAL_APART]
    rivals += [p.ranked for p in ranked if rotation_error(p.camera.R, best.camera.R) >= RIVAL_APART][:1]
    typical = float(np.median([p.ranked for p in ranked]))
    return {
        "sphere_cost": best.cost,
        "margin": (min(rivals) - best.cost) / max(min(rivals), 1e-9) if rivals else 1.0,
        "rank_lead": 1.0 - best.cost / max(typical, 1e-9),
    }


def sphere_fit(work: npt.NDArray[np.uint8], model: VehicleModel, searched: SphereSearch, options: RegistrationOptions,
               renderer: Renderer, box: Box | None = None, pose: Pose | None = None) -> Fit:
    """The search's pose as a :class:`~vehicle_pose.registration.fit.Fit`: the working photo
    segmented by GrabCut seeded by the pose (the client's grown box may be claimed too), and the
    named loss of the pose on that mask, so that every registration reports the same measure."""
    Hf, Wf = work.shape[:2]
    pose = pose if pose is not None else searched.best
    camera = pose.camera
    t = time.perf_counter()
    region = None if box is None else box_mask(box, Wf, Hf, options.segmentation.box_margin)
    mask = None
    if options.segmentation.grabcut:
        mask = resegment(work, model, camera, options.segmentation, renderer, region, max(Wf, Hf))
    if mask is None:
        mask = silhouette(model, camera, renderer) if options.segmentation.grabcut else np.ones((Hf, Wf), bool)
    grabcut = time.perf_counter() - t
    loss, luminance = losses_at(work, mask, camera, model, options, renderer, Wf, Hf)
    size = _search_size(work, options)
    evaluations = sum(p.evaluations for p in searched.refined) + len(searched.ranked)
    level = LevelReport(size[0], size[1], model.exterior(options.pyramid.min_faces, renderer).n_faces, evaluations, 0,
                        loss, searched.seconds, pose.cost, luminance)
    return Fit(camera, [level], mask, grabcut)


def sphere_pose(work: npt.NDArray[np.uint8], model: VehicleModel, options: RegistrationOptions, renderer: Renderer,
                optimizer: Optimizer, *, init: Camera | None = None, box: Box | None = None,
                foreground: npt.NDArray[np.bool_] | None = None, progress: Progress | None = None,
                focal_band: tuple[float, float] | None = None,
                deadline: Deadline | None = None) -> tuple[Fit, SphereSearch, str]:
    """The search's pose, polished by the shading fit where the shading may explain the photo,
    else voted on by the search at other sizes.

    The search's pose is segmented and scored by the named loss (:func:`sphere_fit`); where
    that loss over its maximum is at most ``shading_polish`` (a render, a matte car), the
    coarse-to-fine shading fit runs from it and its pose is kept when its loss is at most
    ``shading_trust`` (the loss then explains the photo, and fits it more precisely than the
    edges), once the shading has judged it against its rival (:func:`_against_rival`, where
    ``rival_polish``). Else the edges decide: without a start camera and with ``sphere_twin``,
    each search's best pose is weighed against its half-turn twin (:func:`_with_twin`); with
    ``sphere_votes``, the search runs again at
    those sizes in turn, about the target of its pose, until the poses of more than half of all
    the sizes agree (or none is left), and the sizes vote (:func:`_vote`); the other sizes'
    poses are offered to the shading in the same way (the vote's first), and the first it
    explains stands; without a hint and with ``sphere_frame_choice``, the frame's own best pose
    stands last where it costs less on the frame and the decided pose's target together
    (:func:`_frame_choice`). Returns the fit, the
    search and which stage's pose it is (``shading`` or ``structure``). ``focal_band`` as for
    :func:`sphere_search`; the shading fit searches the focal length within it (where the
    shading explains the photo, it tells the focal length more precisely than a rounded EXIF).
    ``deadline`` is offered the search's pose before the polish.
    """
    templates = model.templates(renderer)
    searched = sphere_search(work, model, templates, options, renderer, optimizer, init=init, box=box,
                             progress=progress, focal_band=focal_band)
    first = searched
    if deadline is not None:
        deadline.offer(searched.best.camera, "structure")
    polished = _shading(work, model, searched, options, renderer, optimizer, box, foreground, progress, focal_band)
    if polished is not None:
        return polished
    # The edges decide: each size's search weighs its best pose against that pose's half-turn
    # twin (without a start camera); the shading is offered each search as it was found.
    twinned = options.search.sphere_twin and init is None

    def decided(found: SphereSearch) -> SphereSearch:
        return _with_twin(found, model, options, optimizer, progress, focal_band) if twinned else found

    votes = options.search.sphere_votes
    if not votes:
        searched = decided(searched)
        weighed = searched
    else:
        searches, edges = [searched], [decided(searched)]
        weighed = edges[0]
        scored = [_search_size(work, options)]  # the size each search scored at (never enlarged)
        for size in votes:
            sized = options.replace(sphere_size=int(size))
            scored.append(_search_size(work, sized))
            if scored[-1] in scored[:-1]:
                # A photo smaller than this size is searched at its own size, as already done:
                # the same search would find the same pose (about the same target). Its vote is
                # that search's, and it is not searched or offered to the shading again.
                k = scored.index(scored[-1])
                searches.append(searches[k])
                edges.append(edges[k])
            else:
                searches.append(sphere_search(work, model, templates, sized, renderer, optimizer, init=init, box=box,
                                              progress=progress, focal_band=focal_band, targets=searched.targets,
                                              only=edges[0].best.target))
                edges.append(decided(searches[-1]))
            if max(len(g) for g in _groups(edges)) > (1 + len(votes)) / 2:
                break  # a majority of all the sizes: the rest cannot outvote it
        voted = _vote(edges)
        i = next(j for j, e in enumerate(edges) if e.best is voted.best)
        # The shading is offered every size's search it has not seen, the vote's first: a pose
        # it explains stands, as the first size's would have.
        offered = [searches[i]] if i > 0 else []
        offered += [s for s in _distinct(searches)[1:] if s is not searches[i]]
        for other in offered:
            polished = _shading(work, model, other, options, renderer, optimizer, box, foreground, progress,
                                focal_band)
            if polished is not None:
                fitted, confirmed, stage = polished
                confirmed = replace(confirmed, seconds=_seconds(edges))
                confirmed.checks["sizes_agree"] = _agreement(confirmed.best, edges)
                return fitted, confirmed, stage
        searched = voted
    if options.search.sphere_frame_choice and init is None and box is None:
        searched = _frame_choice(searched, first, weighed, work, model, options, optimizer, progress, focal_band)
    return sphere_fit(work, model, searched, options, renderer, box), searched, "structure"


def _frame_choice(searched: SphereSearch, first: SphereSearch, weighed: SphereSearch, work: npt.NDArray[np.uint8],
                  model: VehicleModel, options: RegistrationOptions, optimizer: Optimizer,
                  progress: Progress | None, focal_band: tuple[float, float] | None) -> SphereSearch:
    """The search decided by the edges, or the frame's own pose where it costs less on the frame
    and the decided pose's target together.

    Each target's poses are scored by their own target's cost, and a target that holds a lamp
    or the number plate pays ``sphere_clutter`` for each photo edge outside it: less than the
    whole car's pose pays for the edges a CAD model close but not exact leaves unexplained, so
    a model shrunk onto part of the car can win. Each region's cost leans its own way (the
    frame's towards a model that covers the clutter, a small region's towards a model shrunk
    into it), so the two poses are priced on both: the frame target's best pose of the first
    search (``first``), weighed against its half-turn twin on the frame as each search's best is
    (:func:`_with_twin`), stands where its summed cost is the lower
    (``docs/decisions/0063-the-frame-s-pose-weighed-last.md``). The choice is the last step: the
    sizes' vote and the shading's offers are as before. ``weighed`` is the first search as the
    edges decided it (its best pose weighed against its twin): where that best pose is the
    frame's, its twin is not refined again."""
    frame = next((k for k, t in enumerate(first.targets) if t.box == _frame_box(work)), None)
    own = [p for p in first.refined if p.target == frame]
    if frame is None or not own:
        return searched
    if options.search.sphere_twin and first.best.target == frame:
        # The first search's best pose is the frame's own: the edges have weighed it against its
        # twin already (the same refinement from the same pose).
        framed = replace(weighed, refined=[p for p in weighed.refined if p.target == frame], seconds=first.seconds)
    else:
        framed = replace(first, refined=own)
        if options.search.sphere_twin:
            framed = _with_twin(framed, model, options, optimizer, progress, focal_band)
    seconds = searched.seconds + framed.seconds - first.seconds
    if framed.best is searched.best:
        return replace(searched, seconds=seconds)  # the decided pose is the frame's own
    # Both poses priced on both regions: the frame, and the target the decided pose was found in
    # (one region, priced once, where that target is the frame).
    both = [first.costs[k] for k in {frame, searched.best.target}]
    better = sum(c(framed.best.camera) for c in both) < sum(c(searched.best.camera) for c in both)
    chosen = _promoted(searched, framed.best) if better else searched
    return replace(chosen, seconds=seconds)


def _shading(work: npt.NDArray[np.uint8], model: VehicleModel, searched: SphereSearch, options: RegistrationOptions,
             renderer: Renderer, optimizer: Optimizer, box: Box | None, foreground: npt.NDArray[np.bool_] | None,
             progress: Progress | None, focal_band: tuple[float, float] | None
             ) -> tuple[Fit, SphereSearch, str] | None:
    """The shading fit from the search's refined pose that the shading explains best, where it
    may explain it; its fit, the search with that pose first, and ``shading`` where the final
    loss is credible (:func:`sphere_pose`); else None."""
    st = options.structure
    # Each refined pose scored by the named loss on its target's segmentation: where one is
    # explained by the shading (its loss over its maximum at most shading_polish), the shading
    # fit polishes it, and its pose stands where its final loss is credible.
    bests = searched.refined
    w, h = _search_size(work, options)
    # On the luminance, where the thresholds are set (Fit.share), whatever loss the fit minimises:
    # the luminance's maximum is 1, so the loss is its share.
    gray = replace(options, color=False)
    shares = [loss_at(work, searched.targets[p.target].mask, p.camera, model, gray, renderer, w, h) for p in bests]
    k = int(np.argmin(shares))
    if shares[k] > st.shading_polish:
        return None
    plan = FitPlan(options.pyramid.coarse_to_fine, st.polish_evaluations,
                   options.segmentation.grabcut and options.segmentation.resegment, options.terms.edge_weight,
                   focal_band=focal_band, focal_prior=options.search.exif_refine)

    def polish(pose: Pose) -> Fit:
        # The polish's levels are not offered to the deadline: its pose stands only if credible.
        return fit(work, model, pose.camera, options, plan, renderer, optimizer, progress, foreground, box=box)

    polished = polish(bests[k])
    if polished.share(work, options.color) > st.shading_trust:
        return None
    if not st.rival_polish:
        return polished, _promoted(searched, bests[k]), "shading"
    polished, k, margin = _against_rival(polished, k, bests, shares, polish, work, options)
    promoted = _promoted(searched, bests[k])
    promoted.checks["shading_margin"] = margin
    return polished, promoted, "shading"


def _groups(searches: list[SphereSearch]) -> list[list[int]]:
    """For each search, the searches whose best pose is within :data:`RIVAL_APART` of its own."""
    bests = [s.best for s in searches]
    return [[j for j, q in enumerate(bests) if rotation_error(p.camera.R, q.camera.R) < RIVAL_APART] for p in bests]


def _distinct(searches: list[SphereSearch]) -> list[SphereSearch]:
    """The searches run, each once, in order (a size searched already votes with the same
    search)."""
    out: list[SphereSearch] = []
    for s in searches:
        if all(s is not o for o in out):
            out.append(s)
    return out


def _seconds(searches: list[SphereSearch]) -> float:
    """The time of the searches run (each counted once)."""
    return sum(s.seconds for s in _distinct(searches))


def _agreement(pose: Pose, searches: list[SphereSearch]) -> float:
    """The share of the searches whose best pose is within :data:`RIVAL_APART` of ``pose``."""
    return sum(rotation_error(pose.camera.R, s.best.camera.R) < RIVAL_APART for s in searches) / len(searches)


def _vote(searches: list[SphereSearch]) -> SphereSearch:
    """The sizes' vote on the pose (the first search is at the working ``sphere_size``).

    The edges seen at another size are the same edges, placed and thinned a little otherwise: a
    pose they decide holds at every size, and where the best poses of two sizes are more than
    :data:`RIVAL_APART` degrees apart, the edges cannot tell them apart (a near tie, most often
    a pose and its half-turn twin). The working size's search stands, unless a group of the
    other sizes' best poses within :data:`RIVAL_APART` of each other outnumbers the working
    size's own group: then the search whose pose of that group costs least at the working size
    (the targets are the same at every size). Its checks gain ``sizes_agree``, the share of the
    sizes whose best pose is within :data:`RIVAL_APART` of its pose, and its time is that of all
    the searches run (``docs/decisions/0036-sizes-vote.md``)."""
    first = searches[0]
    bests = [s.best for s in searches]
    groups = _groups(searches)
    largest = max(len(g) for g in groups)
    i = 0
    if len(groups[0]) < largest:
        members = {j for g in groups if len(g) == largest for j in g}
        i = min(sorted(members), key=lambda j: first.costs[bests[j].target](bests[j].camera))
    voted = replace(searches[i], checks=dict(searches[i].checks), seconds=_seconds(searches))
    voted.checks["sizes_agree"] = len(groups[i]) / len(searches)
    return voted


def _against_rival(polished: Fit, k: int, bests: list[Pose], shares: list[float], polish: Callable[[Pose], Fit],
                   work: npt.NDArray[np.uint8], options: RegistrationOptions) -> tuple[Fit, int, float]:
    """The shading's own verdict between the polished pose (of refined pose ``k``) and its rival:
    the refined pose at least :data:`RIVAL_APART` degrees away whose loss (``shares``) is lowest,
    polished too where the shading may explain it (at most ``shading_polish``). The lower final
    loss wins; the relative margin between the two losses is the winner's uniqueness, 1 where no
    rival is polished (none apart, none the shading may explain, or none a fit can start from)
    or where the rival's polish ends within :data:`RIVAL_APART` of the polished pose (the same
    pose found twice). Returns the winning fit, its refined pose's index and the
    margin (``docs/decisions/0033-the-shading-judges-its-rival.md``)."""
    rivals = [i for i, p in enumerate(bests) if rotation_error(p.camera.R, bests[k].camera.R) >= RIVAL_APART]
    if not rivals:
        return polished, k, 1.0
    j = min(rivals, key=lambda i: shares[i])
    if shares[j] > options.structure.shading_polish:
        return polished, k, 1.0
    try:
        other = polish(bests[j])
    except PoseError:
        return polished, k, 1.0  # no fit from the rival (its wheels' side not in view): no rival
    mine, theirs = (f.share(work, options.color) for f in (polished, other))
    apart = rotation_error(other.camera.R, polished.camera.R)
    if theirs < mine:
        polished, k, mine, theirs = other, j, theirs, mine
    if apart < RIVAL_APART:
        return polished, k, 1.0
    return polished, k, (theirs - mine) / max(theirs, 1e-9)


def _promoted(searched: SphereSearch, pose: Pose) -> SphereSearch:
    """The search with ``pose`` first (the one the shading fit confirmed), its checks about it."""
    refined = [pose] + [p for p in searched.refined if p is not pose]
    rivals = [p.cost for p in refined[1:] if rotation_error(p.camera.R, pose.camera.R) >= RIVAL_APART]
    checks = dict(searched.checks)
    checks["sphere_cost"] = pose.cost
    checks["margin"] = (min(rivals) - pose.cost) / max(min(rivals), 1e-9) if rivals else 1.0
    return replace(searched, refined=refined, checks=checks)


def box_agreement(camera: Camera, model: VehicleModel, box: Box) -> dict[str, float]:
    """``box_agreement``: the IoU of the box of the pose's projection, cut to the frame, with the
    client's ``box`` (both in the camera's pixels); 0 where the model is not in view."""
    seen = _seen_box(camera, model, 1.0)
    return {"box_agreement": 0.0 if seen is None else _box_iou(seen, box)}


def _ring(views: npt.NDArray[np.float64]) -> npt.NDArray[np.int64]:
    """The templates of the edge evidence's ring (rows of ``views``: azimuth, elevation,
    distance): at the grid's elevation nearest 8 degrees and distance nearest 4 radii, the view
    nearest each of 0, 30, ..., 330 degrees of azimuth, whatever the grid's step (each view
    once, in the grid's order)."""
    elevation = views[np.argmin(np.abs(views[:, 1] - 8.0)), 1]
    distance = views[np.argmin(np.abs(views[:, 2] - 4.0)), 2]
    level = np.flatnonzero((views[:, 1] == elevation) & (views[:, 2] == distance))
    off = np.abs(np.mod(views[level, 0][None, :] - np.arange(0.0, 360.0, 30.0)[:, None] + 180.0, 360.0) - 180.0)
    return np.unique(level[np.argmin(off, axis=1)])


def edge_evidence(work: npt.NDArray[np.uint8], model: VehicleModel, camera: Camera, options: RegistrationOptions,
                  renderer: Renderer) -> dict[str, float]:
    """Evidence of a vehicle where a pose puts it: the pose's two-way chamfer over the box of its
    projection (cut to the frame), ``two_way``, and its lead over the median of a ring of views
    of the model placed in the same box (the templates nearest every 30 degrees of azimuth),
    ``edge_lead``.

    A photo whose edges a vehicle explains leads by 0.3-0.6 at the right pose; on a photo of
    noise, or one without edges, every view fits alike and the lead is about 0.
    """
    w, h = _search_size(work, options)
    cam = camera.scaled(w, h)
    box = _seen_box(cam, model, 2.0)
    if box is None:
        return {"two_way": 2.0, "edge_lead": 0.0}
    image = resized(work, w, h)
    chamfer = TwoWayChamfer(image, region=box, tau=options.structure.anchor_tau, crease=options.terms.edge_crease)
    mesh = model.exterior(options.pyramid.min_faces, renderer)
    cost = chamfer(renderer.render(mesh, cam))
    templates = model.templates(renderer)
    ring = _ring(templates.views)
    bw, bh = box[2] - box[0], box[3] - box[1]
    ring_views = []
    for t in ring:
        tb = templates.boxes[t]
        f = float(np.sqrt(bw / (tb[2] - tb[0]) * bh / (tb[3] - tb[1])))
        u = 0.5 * (box[0] + box[2]) - f * 0.5 * (tb[0] + tb[2])
        v = 0.5 * (box[1] + box[3]) - f * 0.5 * (tb[1] + tb[3])
        ring_views.append(templates.camera(int(t), f, u, v, (float(cam.K[0, 2]), float(cam.K[1, 2])), w, h))
    others = [chamfer(frame) for frame in renderer.render_many(mesh, ring_views)]
    typical = float(np.median(others)) if others else cost
    return {"two_way": float(cost), "edge_lead": float(1.0 - cost / max(typical, 1e-9))}
