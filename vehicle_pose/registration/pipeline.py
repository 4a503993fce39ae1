"""The registration pipeline (method.md §5): start pose, GrabCut, coarse-to-fine simplex search.

>>> result = register(photo_rgb, model, init_camera=camera)      # doctest: +SKIP
>>> result.camera.K, result.camera.R, result.camera.t             # doctest: +SKIP
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from vehicle_pose.geometry.camera import Camera
from vehicle_pose.loss.edges import EdgeLoss
from vehicle_pose.errors import BlankPhotoError, CameraError, PoseError
from vehicle_pose.search.views import (
    Box,
    Candidate,
    box_overflow,
    distinct,
    fit_to_box,
    parse_bbox,
    refocus,
    rotation_angle,
    score_cameras,
    view_camera,
    view_search,
)
from vehicle_pose.model.library import VehicleModel
from vehicle_pose.loss.invariant import make_target
from vehicle_pose.loss.registry import LOSSES, make_loss
from vehicle_pose.search.optimize import OPTIMIZERS, Optimizer, OptimizeResult
from vehicle_pose.registration.options import RegistrationOptions
from vehicle_pose.geometry.parametrize import PARAMETRIZATIONS, Parametrization, ThetaParams, ViewParams
from vehicle_pose.photo import is_gray
from vehicle_pose.geometry.pose import Side, Theta, camera_to_theta, visible_side
from vehicle_pose.segment.region import VehicleRegion, find_vehicle
from vehicle_pose.render.renderer import Renderer
from vehicle_pose.segment.grabcut import grabcut_foreground
from vehicle_pose.search.wheels import detect_wheels, wheel_candidates
from vehicle_pose.geometry.window import Window

__all__ = ["RegistrationOptions", "LevelReport", "RegistrationResult", "register", "confidence"]

Progress = Callable[[str, int, float], None]
_INVALID = 10.0
# A photo whose values all lie within this many levels is blank (sensor noise of a flat frame).
_BLANK_RANGE = 2
# Faces of the mesh whose silhouette seeds GrabCut and is checked against the region.
_OUTLINE_FACES = 16384


@dataclass(frozen=True)
class LevelReport:
    """What one pyramid level did. ``loss`` is the named loss at the level's pose,
    ``objective`` what the search minimised: the loss plus the edge and box terms."""

    width: int
    height: int
    faces: int
    evaluations: int
    restarts: int
    loss: float
    seconds: float
    objective: float


@dataclass
class RegistrationResult:
    """A registered pose and how it was found.

    ``camera`` maps mesh coordinates to pixels of the photo as given (OpenCV convention);
    ``foreground`` is the GrabCut mask at the photo's size. ``start_source`` is the hint the
    client gave (``init_camera``, ``bbox`` or ``none``), ``start_method`` how the winning start
    was found (``given``, ``view-search`` or ``wheels``). ``confidence`` (in [0, 1], see
    :func:`confidence`) and ``failed`` judge a pose found without a start camera; ``checks``
    holds the measures behind them (and, for every run, ``foreground_iou``, the final
    silhouette against the final GrabCut mask, and ``loss``, the final loss over its maximum;
    ``passes`` is 2 when a second search ran);
    ``candidates`` lists the screened starts. ``evaluations`` and ``restarts`` count every
    search run, screening included; ``levels`` are the winning pose's levels.
    """

    camera: Camera
    theta: Theta
    loss: float
    evaluations: int
    restarts: int
    seconds: float
    model: VehicleModel
    start_source: str
    start_camera: Camera
    levels: list[LevelReport]
    options: RegistrationOptions
    foreground: npt.NDArray[np.bool_] = field(repr=False)
    timings: dict[str, float] = field(default_factory=dict)
    start_method: str = "given"
    confidence: float | None = None
    failed: bool = False
    checks: dict[str, float] = field(default_factory=dict)
    candidates: list[dict[str, Any]] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """The JSON result: camera, theta, BOP-style fields, loss, counts, timings."""
        cam = self.camera
        info = self.model.info
        return {
            "camera": cam.to_dict(),
            "theta": self.theta.to_dict(),
            "loss": self.loss,
            "loss_name": self.options.loss,
            "evaluations": self.evaluations,
            "restarts": self.restarts,
            "seconds": self.seconds,
            "model": {
                "id": info.id,
                "name": info.name,
                "units": info.units,
                "wheels": self.model.wheels.to_dict(),
                "estimated": list(info.estimated),
            },
            "confidence": self.confidence,
            "failed": self.failed,
            "checks": self.checks,
            "start": {
                "source": self.start_source,
                "method": self.start_method,
                "camera": self.start_camera.to_dict(),
                "candidates": self.candidates,
            },
            "levels": [vars(level) for level in self.levels],
            "timings": self.timings,
            "options": asdict(self.options),
            "cam_R_m2c": cam.R.reshape(-1).tolist(),
            "cam_t_m2c": cam.t.tolist(),
            "cam_K": cam.K.reshape(-1).tolist(),
        }


def _resize(rgb: npt.NDArray[np.uint8], width: int, height: int) -> npt.NDArray[np.uint8]:
    if (rgb.shape[1], rgb.shape[0]) == (width, height):
        return rgb
    return cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA)


def _resize_mask(mask: npt.NDArray[np.bool_], width: int, height: int) -> npt.NDArray[np.bool_]:
    if (mask.shape[1], mask.shape[0]) == (width, height):
        return mask
    return cv2.resize(mask.astype(np.uint8), (width, height), interpolation=cv2.INTER_NEAREST) > 0


def _level_sizes(width: int, height: int, options: RegistrationOptions) -> list[tuple[int, int]]:
    longer = max(width, height)
    sizes = []
    if options.coarse_to_fine:
        for size in options.coarse_sizes:
            if size < 0.75 * longer:
                s = size / longer
                sizes.append((max(8, round(width * s)), max(8, round(height * s))))
    return [*sizes, (width, height)]


def _face_budget(pixels: float, options: RegistrationOptions) -> int:
    wanted = max(float(options.min_faces), options.faces_per_pixel * pixels)
    return int(2 ** np.ceil(np.log2(wanted)))


@dataclass
class _Fit:
    """One single-start registration at working size."""

    camera: Camera
    levels: list[LevelReport]
    foreground: npt.NDArray[np.bool_]
    grabcut_seconds: float

    @property
    def loss(self) -> float:
        return self.levels[-1].loss

    @property
    def objective(self) -> float:
        return self.levels[-1].objective


def _fit(
    work: npt.NDArray[np.uint8],
    model: VehicleModel,
    start: Camera,
    options: RegistrationOptions,
    renderer: Renderer,
    optimizer: Optimizer,
    progress: Progress | None,
    foreground: npt.NDArray[np.bool_] | None,
    stage_prefix: str = "",
    *,
    step_scale: float = 1.0,
    box: Box | None = None,
) -> _Fit:
    """Register from one start camera on ``work`` (already at working size).

    ``step_scale`` scales the first level's simplex. ``box`` (working-size pixels), the
    client's box of the vehicle, widens what GrabCut may call foreground beyond the grown start
    silhouette.
    """
    Hf, Wf = work.shape[:2]
    start = start.scaled(Wf, Hf)
    side: Side
    if options.side in ("left", "right"):
        side = options.side  # type: ignore[assignment]
    else:
        side = visible_side(start, model.wheels.side("left"))
    geometry = model.wheels.side(side)

    silhouette = renderer.render(model.lod(_OUTLINE_FACES), start).coverage
    if silhouette.sum() < 16:
        raise PoseError("the start pose puts the model off-screen or behind the camera")

    t = time.perf_counter()
    segment_again = options.grabcut and options.resegment and foreground is None
    region = None if box is None else _box_mask(box, Wf, Hf, options.box_margin)
    if foreground is not None:
        foreground = _resize_mask(foreground, Wf, Hf)
    elif options.grabcut:
        foreground = grabcut_foreground(work, silhouette, margin=options.grabcut_margin, region=region)
    else:
        foreground = np.ones((Hf, Wf), bool)
    grabcut_seconds = time.perf_counter() - t

    camera = start
    levels: list[LevelReport] = []
    # The box term's points, sampled once per fit and only when the term is on (the no-hint
    # chain runs a fit per screened start, without a box).
    box_points = model.mesh.sample_points(600) if box is not None and options.box_weight > 0 else None
    area = max(float(silhouette.sum()), 1.0)
    fine = min(1.0, float(np.sqrt(options.max_pixels / area))) if options.max_pixels > 0 else 1.0
    sizes = _level_sizes(max(8, round(Wf * fine)), max(8, round(Hf * fine)), options)
    for li, (w, h) in enumerate(sizes):
        t = time.perf_counter()
        # Faces hidden from every outside view (the cabin of many CAD cars) are dropped: they
        # never reach a pixel but cost the rasteriser as much as visible ones.
        mesh = model.exterior(_face_budget(float(silhouette.sum()) * (w * h) / (Wf * Hf), options), renderer)
        target = make_target(_resize(work, w, h), _resize_mask(foreground, w, h), color=options.color)
        loss_fn = make_loss(options.loss, target)
        edge_fn = None
        if options.edge_weight > 0:
            edge_fn = EdgeLoss(_resize(work, w, h), foreground=target.foreground, crease=options.edge_crease)
        stage = f"{stage_prefix}level {li + 1}/{len(sizes)} ({w}x{h})"
        level_box = None
        if box is not None and box_points is not None:
            level_box = (box[0] * w / Wf, box[1] * h / Hf, box[2] * w / Wf, box[3] * h / Hf)
        counter = [0]

        def search(reference: Camera, budget: int) -> tuple[OptimizeResult, Parametrization]:
            params: Parametrization
            if options.parametrization == "view":
                params = _view_params(reference.scaled(w, h), model, options.dolly_pivot)
            else:
                params = ThetaParams(reference.scaled(w, h), geometry, side)
            try:
                x0 = params.start()
            except PoseError:
                raise PoseError(f"the start pose does not show the {side} side's wheels") from None

            def objective(x: npt.NDArray[np.float64]) -> float:
                try:
                    cam = params.camera(x)
                except (PoseError, CameraError):
                    return _INVALID
                frame = renderer.render(mesh, cam)
                value = float(loss_fn(frame))
                if edge_fn is not None:
                    value += options.edge_weight * edge_fn(frame)
                if level_box is not None and box_points is not None:
                    value += options.box_weight * box_overflow(cam, box_points, level_box, options.box_tolerance,
                                                                options.box_shortfall)
                counter[0] += 1
                if progress is not None and counter[0] % 20 == 0:
                    progress(stage, counter[0], value)
                return value

            steps = params.steps() * step_scale * 0.4**li
            return optimizer(objective, x0, steps, max_evaluations=budget), params

        budget = options.fine_evaluations if li == len(sizes) - 1 and li > 0 else options.max_evaluations
        runs = [search(camera, budget)]
        if li == 1 and options.focal_starts:
            # The second level also probes dolly zooms of the first level's pose, on the same
            # mask (the perspective is what a simplex corrects least); a
            # probe that beats the main search is searched on.
            probes = [search(ref, options.focal_evaluations)
                      for ref in _dolly_zooms(camera, model, _probe_factors(camera, options), options.dolly_pivot)]
            best_probe = min(probes, key=lambda e: e[0].fun)
            runs += probes
            if best_probe[0].fun < runs[0][0].fun * (1.0 + options.probe_margin):
                runs.append(search(best_probe[1].camera(best_probe[0].x).scaled(Wf, Hf),
                                   options.max_evaluations - options.focal_evaluations))
        res, params = min(runs, key=lambda e: e[0].fun)
        if len(runs) > 1:
            res = replace(res, evaluations=sum(r.evaluations for r, _ in runs), restarts=sum(r.restarts for r, _ in runs))
        camera = params.camera(res.x).scaled(Wf, Hf)
        loss = res.fun
        if edge_fn is not None or level_box is not None:
            loss = float(loss_fn(renderer.render(mesh, camera.scaled(w, h))))
        levels.append(LevelReport(w, h, mesh.n_faces, res.evaluations, res.restarts, loss, time.perf_counter() - t, res.fun))
        if progress is not None:
            progress(stage, res.evaluations, res.fun)
        if segment_again and li < len(sizes) - 1:
            t = time.perf_counter()
            # At the next level's resolution: a mask upsampled from a coarser GrabCut
            # misplaces the outline by a pixel, and the pose follows the mask (synthetic
            # cases ended 0.5-1.2 px off with a 320-pixel mask, below 0.1 px with this).
            again = _resegment(work, model, camera, options, renderer, region, max(sizes[li + 1]))
            foreground = foreground if again is None else again
            grabcut_seconds += time.perf_counter() - t
    return _Fit(camera, levels, foreground, grabcut_seconds)


def _resegment(
    work: npt.NDArray[np.uint8],
    model: VehicleModel,
    camera: Camera,
    options: RegistrationOptions,
    renderer: Renderer,
    region: npt.NDArray[np.bool_] | None,
    size: int,
) -> npt.NDArray[np.bool_] | None:
    """GrabCut seeded by a pose already close (its shrunk silhouette certain foreground), run
    at ``size`` pixels (at least 320) on the longer side; None when the pose shows too little."""
    current = renderer.render(model.lod(_OUTLINE_FACES), camera).coverage
    if current.sum() < 16:
        return None
    return grabcut_foreground(work, current, margin=options.resegment_margin, sure_core=True,
                              iterations=options.resegment_iterations, region=region, max_size=max(320, size))


def _projected_box(model: VehicleModel, camera: Camera) -> Box | None:
    """The box of the model's projection, None when part of it is behind the camera."""
    uv = camera.project(model.mesh.sample_points(600))
    if not np.all(np.isfinite(uv)):
        return None
    return float(uv[:, 0].min()), float(uv[:, 1].min()), float(uv[:, 0].max()), float(uv[:, 1].max())


def _union(a: Box, b: Box | None) -> Box:
    """The smallest box holding both (``a`` when ``b`` is None)."""
    if b is None:
        return a
    return min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3])


def _probe_factors(camera: Camera, options: RegistrationOptions) -> list[float]:
    """Focal factors of the perspective probes: ``focal_starts``, and when the focal length is
    outside ``focal_range`` (image widths) one more to the range's geometric middle."""
    factors = list(options.focal_starts)
    lo, hi = (r * camera.width for r in options.focal_range)
    if not lo <= camera.focal <= hi:
        factors.append(float(np.sqrt(lo * hi)) / camera.focal)
    return factors


def _named_optimizer(name: str) -> Optimizer:
    """A fresh optimiser from :data:`OPTIMIZERS`; ValueError for an unknown name."""
    if name not in OPTIMIZERS:
        raise ValueError(f"unknown optimizer {name!r}; choose one of {', '.join(OPTIMIZERS)}")
    return OPTIMIZERS[name]()


def _window_margin(options: RegistrationOptions) -> float | None:
    """The start searches' window margin; the theta coordinates need the whole image (their
    principal point is its centre)."""
    return options.window_margin if options.parametrization == "view" else None


def _view_params(reference: Camera, model: VehicleModel, pivot: float) -> ViewParams:
    """View coordinates about ``reference``, the dolly zoom pivoted ``pivot`` bounding-sphere
    radii in front of the model's centre."""
    centre, radius = model.mesh.sphere
    return ViewParams(reference, centre, pivot * radius)


def _dolly_zooms(camera: Camera, model: VehicleModel, factors: Sequence[float], pivot: float = 0.0) -> list[Camera]:
    """The camera with its focal length times each factor and the depth following: the same
    centre and orientation in the image, and the same size at ``pivot`` bounding-sphere radii
    in front of the model's centre (see :class:`ViewParams`), another perspective."""
    view = _view_params(camera, model, pivot)
    out = []
    for factor in factors:
        x = np.zeros(7)
        x[6] = np.log(factor)
        out.append(view.camera(x))
    return out


def _box_mask(box: Box, width: int, height: int, margin: float) -> npt.NDArray[np.bool_]:
    """The box grown by ``margin`` of its diagonal, as an (height, width) mask."""
    x0, y0, x1, y1 = box
    g = margin * float(np.hypot(x1 - x0, y1 - y0))
    mask = np.zeros((height, width), bool)
    mask[max(0, int(y0 - g)) : max(0, int(np.ceil(y1 + g)) + 1), max(0, int(x0 - g)) : max(0, int(np.ceil(x1 + g)) + 1)] = True
    return mask


def _iou(a: npt.NDArray[np.bool_], b: npt.NDArray[np.bool_]) -> float:
    union = float((a | b).sum())
    return float((a & b).sum()) / union if union else 0.0


def confidence(checks: dict[str, float]) -> float:
    """How credible a pose found without a start camera is, in [0, 1]; below 0.5 is ``failed``.

    The weakest of three scores, each 0.5 at its threshold:

    - fit: the final loss over its maximum, 1 up to 0.10, 0.5 at 0.15, 0 from 0.20;
    - uniqueness: the relative loss margin over the best alternative at least 15 degrees away,
      0.5 at 0.15, 1 from 0.35 (``agreement``, the share of other starts that converged to
      the same pose, is reported but does not count: a wrong front/back twin can gather
      starts as well);
    - region: the final silhouette's IoU with the vehicle's region found before any pose was
      known, 0.5 at 0.7, 1 from 0.9.

    The thresholds were set on the photoreal benchmark (docs/benchmarks.md), where every wrong
    pose fails one of them.
    """
    fit = (0.20 - checks.get("loss", 1.0)) / 0.10
    unique = (checks.get("margin", 0.0) + 0.05) / 0.40
    region = (checks.get("region_iou", 0.0) - 0.5) / 0.40
    return float(np.clip(min(fit, unique, region), 0.0, 1.0))


def _fit_checks(
    work: npt.NDArray[np.uint8],
    model: VehicleModel,
    fit: _Fit,
    region: VehicleRegion | None,
    options: RegistrationOptions,
    renderer: Renderer,
) -> dict[str, float]:
    """The final pose's silhouette against the region found before any pose was known and
    against its own foreground, and its loss over the loss's maximum."""
    final_sil = renderer.render(model.lod(_OUTLINE_FACES), fit.camera).coverage
    checks = {} if region is None else {"region_iou": _iou(final_sil, region.mask)}
    checks["foreground_iou"] = _iou(final_sil, fit.foreground)
    checks["loss"] = fit.loss / (3.0 if options.color and not is_gray(work) else 1.0)
    return checks


def _search_starts(
    work: npt.NDArray[np.uint8],
    model: VehicleModel,
    rect: Box | None,
    fg: npt.NDArray[np.bool_] | None,
    region: VehicleRegion | None,
    options: RegistrationOptions,
    renderer: Renderer,
) -> tuple[list[Candidate], VehicleRegion]:
    """The vehicle's region (``region`` when given) and the start poses to screen, best first
    (docs/engine.md)."""
    Hf, Wf = work.shape[:2]
    lod_faces = min(4096, options.min_faces)
    if region is not None:
        regions = [region]
    elif fg is not None:
        regions = [VehicleRegion.from_mask(fg)]
    elif rect is not None:
        regions = [find_vehicle(work, rect=rect)]
    else:
        regions = [find_vehicle(work, border=options.region_borders[0])]
    # The region hypothesis whose best view fits it best wins; narrower start rectangles are
    # tried only when the first region is not already well explained by a view.
    margin = _window_margin(options)
    searched = [(view_search(work, reg, model, renderer, max_faces=lod_faces, margin=margin), reg) for reg in regions]
    if region is None and fg is None and rect is None and searched[0][0][0].score > options.region_fit:
        for border in options.region_borders[1:]:
            reg = find_vehicle(work, border=border)
            searched.append((view_search(work, reg, model, renderer, max_faces=lod_faces, margin=margin), reg))
    cands, region = min(searched, key=lambda e: e[0][0].score)
    if options.wheels:
        ellipses = detect_wheels(work, region, max_count=4)
        pairs = wheel_candidates(ellipses, model, Wf, Hf)
        cands += score_cameras(work, region, model, pairs, renderer, max_faces=lod_faces, margin=margin)
    starts = distinct(cands, options.starts)
    best = starts[0]
    if best.source == "view-search":
        # Front and back (and left and right from behind) are the commonest confusion: the
        # best view's twin half a turn away is always screened.
        d = best.detail
        twin = view_camera(model, d["azimuth"] + 180.0, d["elevation"], -d["roll"], region.box, Wf, Hf,
                           best.camera.focal)
        if all(rotation_angle(twin.R, c.camera.R) >= 25.0 for c in starts):
            starts.append(Candidate(twin, "view-search", detail={**d, "azimuth": (d["azimuth"] + 180.0) % 360,
                                                                 "roll": -d["roll"], "twin": 1.0}))
    starts += [
        replace(starts[0], camera=refocus(starts[0].camera, f * Wf, model, region.box),
                detail={**starts[0].detail, "focal_widths": f})
        for f in options.start_focals
    ]
    return starts, region


@dataclass
class _Pass:
    """One search without a start camera: the winning fit and how it was found."""

    fit: _Fit
    levels: list[LevelReport]
    candidate: Candidate
    region: VehicleRegion
    checks: dict[str, float]
    listed: list[dict[str, Any]]
    spent: list[tuple[_Fit, Candidate | None]]
    grabcut_seconds: float
    timings: dict[str, float]


def _search_pass(
    work: npt.NDArray[np.uint8],
    model: VehicleModel,
    rect: Box | None,
    fg: npt.NDArray[np.bool_] | None,
    given_region: VehicleRegion | None,
    options: RegistrationOptions,
    renderer: Renderer,
    optimizer: Optimizer,
    progress: Progress | None,
    stage: str = "",
) -> _Pass:
    """Find the vehicle's region (unless given), search start poses, screen them on a reduced
    photo, refine the best distinct ones and the best of those at working size."""
    Hf, Wf = work.shape[:2]
    timings: dict[str, float] = {}
    listed: list[dict[str, Any]] = []
    spent: list[tuple[_Fit, Candidate | None]] = []
    grabcut_seconds = 0.0
    t = time.perf_counter()
    if progress is not None:
        progress(f"{stage}finding the vehicle", 0, float("nan"))
    starts, region = _search_starts(work, model, rect, fg, given_region, options, renderer)
    timings["start"] = time.perf_counter() - t

    # Screen every start on a reduced photo, then refine the best distinct ones.
    window = Window.around(region.box, Wf, Hf, size=options.screen_size, margin=_window_margin(options))
    small = window.image(work)
    screen_opts = replace(options, max_size=max(window.width, window.height), coarse_to_fine=False,
                          resegment=False, max_evaluations=options.screen_evaluations)
    screened: list[tuple[float, Camera, Candidate]] = []
    for k, cand in enumerate(starts):
        try:
            sf = _fit(small, model, window.camera(cand.camera), screen_opts, renderer, optimizer, progress,
                      None if fg is None else window.mask(fg), f"{stage}start {k + 1}/{len(starts)}: ")
        except PoseError:
            continue
        grabcut_seconds += sf.grabcut_seconds
        spent.append((sf, cand))
        screened.append((sf.objective, window.full_camera(sf.camera), cand))
        listed.append(cand.to_dict() | {"screened_loss": sf.objective})
    if not screened:
        raise PoseError("no start pose puts the model in view of the photo")
    screened.sort(key=lambda e: e[0])
    timings["screen"] = time.perf_counter() - t - timings["start"]
    chosen: list[tuple[float, Camera, Candidate]] = []
    for entry in screened:
        if all(rotation_angle(entry[1].R, c[1].R) >= 10.0 for c in chosen):
            chosen.append(entry)
        if len(chosen) == options.refine:
            break
    # Refine the chosen poses one level up (on a window around each), then the best of
    # them at working size.
    longer = max(Wf, Hf)
    mids = [c for c in options.coarse_sizes if options.screen_size < c < 0.75 * longer]
    fits = []
    refiner = _named_optimizer(options.refine_optimizer)
    for k, (_, cam, cand) in enumerate(chosen):
        prefix = stage + (f"refine {k + 1}/{len(chosen)}: " if len(chosen) > 1 else "refine: ")
        win = Window.around(_union(region.box, _projected_box(model, cam)), Wf, Hf,
                            size=mids[-1] if mids else longer, margin=_window_margin(options))
        mf = _fit(win.image(work), model, win.camera(cam),
                  replace(options, max_size=max(win.width, win.height), coarse_to_fine=False,
                          max_evaluations=options.refine_evaluations),
                  renderer, refiner, progress, None if fg is None else win.mask(fg), prefix)
        spent.append((mf, cand))
        grabcut_seconds += mf.grabcut_seconds
        fits.append((_Fit(win.full_camera(mf.camera), mf.levels, win.full_mask(mf.foreground), 0.0), cand))
    best_mid, best_cand = min(fits, key=lambda e: e[0].objective)
    if mids:
        t = time.perf_counter()
        if fg is not None:
            final_fg = fg
        elif not options.grabcut:
            final_fg = np.ones((Hf, Wf), bool)
        else:
            # Segmented again at working size, seeded by the refined pose (as between levels).
            final_fg = _resegment(work, model, best_mid.camera, options, renderer, None, max(Wf, Hf))
            final_fg = best_mid.foreground if final_fg is None else final_fg
        grabcut_seconds += time.perf_counter() - t
        # The final level polishes a pose within a pixel or two, as the finest level of the
        # hinted chain does, with its budget.
        fit = _fit(work, model, best_mid.camera,
                   replace(options, coarse_to_fine=False, max_evaluations=options.fine_evaluations),
                   renderer, optimizer, progress, final_fg, f"{stage}final: ", step_scale=0.4)
        spent.append((fit, best_cand))
        levels = [*best_mid.levels, *fit.levels]
    else:
        fit = best_mid
        levels = fit.levels

    # Credibility: the margin over alternatives (refined, else screened); agreement reported.
    won = next(e for e in screened if e[2] is best_cand)
    others = [e[0] for e in screened if rotation_angle(e[1].R, fit.camera.R) >= 15.0]
    near = [e for e in screened if e is not won and "focal_widths" not in e[2].detail
            and rotation_angle(e[1].R, fit.camera.R) < 15.0]
    rivals = [f.objective for f, _ in fits if rotation_angle(f.camera.R, best_mid.camera.R) >= 15.0]
    plain = [e for e in screened if "focal_widths" not in e[2].detail]
    checks = {
        "margin": (
            (min(rivals) - best_mid.objective) / max(min(rivals), 1e-9) if rivals
            else (min(others) - won[0]) / max(min(others), 1e-9) if others else 1.0
        ),
        "agreement": len(near) / max(1, len(plain) - 1),
    }
    return _Pass(fit, levels, best_cand, region, checks, listed, spent, grabcut_seconds, timings)


def register(
    photo: npt.NDArray[np.uint8],
    model: VehicleModel,
    *,
    init_camera: Camera | None = None,
    bbox: str | Sequence[float] | None = None,
    options: RegistrationOptions = RegistrationOptions(),
    renderer: Renderer | None = None,
    optimizer: Optimizer | None = None,
    progress: Progress | None = None,
    foreground: npt.NDArray[np.bool_] | None = None,
) -> RegistrationResult:
    """Find the camera that makes the model coincide with the vehicle in the photo.

    With a start camera, one coarse-to-fine search runs from it. Without one (a box, or no hint
    at all), the vehicle's region is found first (GrabCut from the box or a central
    rectangle), start poses come from a view search and from matched wheel ellipses, the best
    ``options.starts`` distinct ones are screened on a reduced photo, the best ``options.refine``
    are refined at full size, and the lowest loss wins, with a confidence and a ``failed`` flag.

    Parameters
    ----------
    photo : (H, W, 3) uint8
        RGB photo (gray photos have three equal channels).
    model : VehicleModel
    init_camera : Camera, optional, keyword-only
        Start pose; a camera for a photo of another size is rescaled to this one.
    bbox : "X0,Y0,X1,Y1" or 4 numbers, optional, keyword-only
        The vehicle's box. Without a start camera the search starts from it; with one, it
        tells GrabCut where the vehicle may be besides the start pose's grown silhouette.
    options : RegistrationOptions, keyword-only
    renderer : Renderer, optional, keyword-only
        Defaults to a renderer on the process's EGL context.
    optimizer : Optimizer, optional, keyword-only
        Overrides ``options.optimizer``.
    progress : callable(stage, evaluations, loss), optional, keyword-only
    foreground : (H, W) bool, optional, keyword-only
        The vehicle's pixels, when the caller knows them; replaces GrabCut.

    Raises
    ------
    CameraError
        The start camera or box is malformed.
    PoseError
        The start pose puts the model behind the camera or off-screen.
    """
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    if photo.ndim != 3 or photo.shape[2] != 3 or photo.dtype != np.uint8:
        raise ValueError("photo must be an (H, W, 3) uint8 RGB array")
    H0, W0 = photo.shape[:2]
    renderer = renderer if renderer is not None else Renderer()
    if optimizer is None:
        optimizer = _named_optimizer(options.optimizer)
    _named_optimizer(options.refine_optimizer)  # an unknown name fails before any work
    if options.parametrization not in PARAMETRIZATIONS:
        raise ValueError(f"unknown parametrization {options.parametrization!r}; choose one of {', '.join(PARAMETRIZATIONS)}")
    if options.loss not in LOSSES:
        raise ValueError(f"unknown loss {options.loss!r}; choose one of {', '.join(LOSSES)}")
    if options.side not in ("auto", "left", "right"):
        raise ValueError(f"side must be 'auto', 'left' or 'right', not {options.side!r}")
    if options.starts < 1 or options.refine < 1:
        raise ValueError("starts and refine must be at least 1")
    if foreground is not None and foreground.shape != (H0, W0):
        raise ValueError(f"foreground mask is {foreground.shape}, the photo {(H0, W0)}")
    pixels = photo.reshape(-1, 3)
    low, high = pixels.min(axis=0), pixels.max(axis=0)
    if int((high.astype(np.int16) - low).max()) <= _BLANK_RANGE:
        raise BlankPhotoError(f"the photo is one flat colour (each channel within {_BLANK_RANGE} levels of "
                              f"RGB {tuple(int(v) for v in low)}): there is nothing to register on")
    if init_camera is not None:
        init_camera.for_photo(W0, H0)  # a camera of another picture fails here, not stretched

    s = min(1.0, options.max_size / max(W0, H0))
    Wf, Hf = max(8, round(W0 * s)), max(8, round(H0 * s))
    work = _resize(photo, Wf, Hf)
    fg = _resize_mask(foreground.astype(bool), Wf, Hf) if foreground is not None else None

    checks: dict[str, float] = {}
    listed: list[dict[str, Any]] = []
    region: VehicleRegion | None = None
    spent: list[tuple[_Fit, Candidate | None]] = []  # every search run, for the evaluation count
    grabcut_seconds = 0.0
    box = parse_bbox(bbox, W0, H0) if bbox is not None else None
    sx, sy = Wf / W0, Hf / H0
    rect: Box | None = None if box is None else (box[0] * sx, box[1] * sy, box[2] * sx, box[3] * sy)
    if init_camera is not None:
        source, method = "init_camera", "given"
        start = init_camera.scaled(Wf, Hf)
        if rect is not None and options.fit_start_to_box:
            # A box is far more precise than a rough pose about where the vehicle is and how
            # large it looks: the start keeps its rotation and focal length and is moved and
            # scaled to fill it (docs/engine.md).
            start = fit_to_box(start, model.mesh.sample_points(600), model.mesh.sphere[0], rect, rounds=5, clip=True)
        timings["start"] = 0.0
        fit = _fit(work, model, start, options, renderer, optimizer, progress, fg, box=rect)
        spent.append((fit, None))
        levels = fit.levels
        grabcut_seconds = fit.grabcut_seconds
    else:
        source = "bbox" if bbox is not None else "none"
        # The edge term is for refining a given start: in the no-hint chain it cost the
        # no-hint photoreal cases: 11 of the first 15 right, against 18 of 20 without it
        # (docs/engine.md).
        options = replace(options, edge_weight=0.0)
        search = _search_pass(work, model, rect, fg, None, options, renderer, optimizer, progress)
        fit, levels, region, checks = search.fit, search.levels, search.region, search.checks
        start, method = search.candidate.camera, search.candidate.source
        listed, spent, grabcut_seconds = search.listed, search.spent, search.grabcut_seconds
        timings.update(search.timings)
        checks |= _fit_checks(work, model, fit, region, options, renderer)
        if fg is None and options.second_pass and confidence(checks) < options.min_confidence:
            # Not credible: search again in the foreground segmented around the pose found,
            # usually closer to the vehicle than the region found with no pose at all, and
            # keep the lower loss (docs/engine.md). The region check stays against the first
            # region, found before any pose was known.
            t = time.perf_counter()
            again = _search_pass(work, model, rect, fg, VehicleRegion.from_mask(fit.foreground), options,
                                 renderer, optimizer, progress, "second pass: ")
            spent += again.spent
            grabcut_seconds += again.grabcut_seconds
            timings["second_pass"] = time.perf_counter() - t
            if again.fit.objective < fit.objective:
                fit, levels, checks, listed = again.fit, again.levels, again.checks, again.listed
                start, method = again.candidate.camera, again.candidate.source
                checks |= _fit_checks(work, model, fit, region, options, renderer)
            checks["passes"] = 2.0
    timings["grabcut"] = grabcut_seconds
    if init_camera is not None:
        checks = _fit_checks(work, model, fit, None, options, renderer)

    camera = fit.camera
    final = camera.scaled(W0, H0)
    side = visible_side(final, model.wheels.side("left"))
    theta = camera_to_theta(final, model.wheels.side(side), side)
    seconds = time.perf_counter() - t_start
    timings["optimize"] = sum(level.seconds for level in levels)
    conf = confidence(checks) if "region_iou" in checks else None
    return RegistrationResult(
        camera=final,
        theta=theta,
        loss=levels[-1].loss,
        evaluations=sum(level.evaluations for f, _ in spent for level in f.levels),
        restarts=sum(level.restarts for f, _ in spent for level in f.levels),
        seconds=seconds,
        model=model,
        start_source=source,
        start_camera=start.scaled(W0, H0),
        levels=levels,
        options=options,
        foreground=_resize_mask(fit.foreground, W0, H0),
        timings=timings,
        start_method=method,
        confidence=conf,
        failed=conf is not None and conf < options.min_confidence,
        checks=checks,
        candidates=listed,
    )
