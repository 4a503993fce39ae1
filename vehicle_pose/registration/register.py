"""``register``: the registration as a short sequence of stages (method.md §5).

>>> result = register(photo_rgb, model, init_camera=camera)      # doctest: +SKIP
>>> result.camera.K, result.camera.R, result.camera.t             # doctest: +SKIP
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from vehicle_pose.errors import BlankPhotoError
from vehicle_pose.geometry.camera import Camera
from vehicle_pose.geometry.pose import camera_to_theta, visible_side
from vehicle_pose.model.library import VehicleModel
from vehicle_pose.photo import ExifFocal, resized, resized_mask
from vehicle_pose.registration.credibility import confidence, fit_checks
from vehicle_pose.registration.deadline import Deadline
from vehicle_pose.registration.fit import Fit, FitPlan, Progress, fit
from vehicle_pose.registration.hypotheses import photo_pose
from vehicle_pose.registration.nohint import search
from vehicle_pose.registration.options import RegistrationOptions
from vehicle_pose.registration.result import LevelReport, RegistrationResult
from vehicle_pose.registration.sphere import box_agreement, edge_evidence, sphere_fit, sphere_pose, sphere_search
from vehicle_pose.registration.structure import find_structure, structure_fit
from vehicle_pose.render.parts import part_map
from vehicle_pose.render.renderer import Renderer
from vehicle_pose.search.optimize import Optimizer, make_optimizer
from vehicle_pose.search.views import Box, fit_to_box, parse_bbox

__all__ = ["register"]

# A photo whose values all lie within this many levels is blank (sensor noise of a flat frame).
_BLANK_RANGE = 2


def _check_photo(photo: npt.NDArray[np.uint8]) -> None:
    """ValueError for an array that is not an RGB photo, BlankPhotoError for one flat colour."""
    if photo.ndim != 3 or photo.shape[2] != 3 or photo.dtype != np.uint8:
        raise ValueError("photo must be an (H, W, 3) uint8 RGB array")
    pixels = photo.reshape(-1, 3)
    low, high = pixels.min(axis=0), pixels.max(axis=0)
    if int((high.astype(np.int16) - low).max()) <= _BLANK_RANGE:
        raise BlankPhotoError(f"the photo is one flat colour (each channel within {_BLANK_RANGE} levels of "
                              f"RGB {tuple(int(v) for v in low)}): there is nothing to register on")


def _given_start(work: npt.NDArray[np.uint8], model: VehicleModel, init_camera: Camera, rect: Box | None,
                 options: RegistrationOptions) -> Camera:
    """The client's start camera at working size; with a box, moved and scaled to fill it."""
    Hf, Wf = work.shape[:2]
    start = init_camera.scaled(Wf, Hf)
    if rect is not None and options.terms.fit_start_to_box:
        # A box is far more precise than a rough pose about where the vehicle is and how
        # large it looks: the start keeps its rotation and focal length and is moved and
        # scaled to fill it (docs/decisions/0006-real-photo-terms.md).
        start = fit_to_box(start, model.mesh.extreme_points(600), model.mesh.sphere[0], rect, rounds=5, clip=True)
    return start


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
    photo_size: tuple[int, int] | None = None,
    exif: ExifFocal | None = None,
    deadline: float | None = None,
) -> RegistrationResult:
    """Find the camera that makes the model coincide with the vehicle in the photo.

    With a start camera, one coarse-to-fine fit runs from it. Without one (a box, or no hint
    at all), the search of :mod:`~vehicle_pose.registration.nohint` finds the vehicle, screens
    start poses and refines the best, and the pose gets a confidence and a ``failed`` flag; a
    pose that is not credible is searched for again around it.

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
    photo_size : (W0, H0), optional, keyword-only
        The photo's own size when ``photo`` is a reduced copy of it (at least the working size,
        of the same shape within a pixel): the start camera, the box and every camera of the
        result are the photo's own.
    exif : ExifFocal, optional, keyword-only
        The focal length the photo's EXIF gives (:func:`~vehicle_pose.photo.read_focal`).
        Without a start camera (whose focal length wins), the view-sphere search starts from it
        and keeps within ``options.search.exif_tolerance`` of it; the result's ``focal`` says
        where its focal length came from, and its ``warnings`` repeat the EXIF's.
    deadline : float, optional, keyword-only
        The moment (``time.monotonic()`` seconds) the registration must end by: checked before
        every loss evaluation (:mod:`~vehicle_pose.registration.deadline`).

    Raises
    ------
    ValueError
        The photo or the foreground is not an array of the right shape.
    BlankPhotoError
        The photo is one flat colour.
    CameraError
        The start camera or box is malformed, or the camera is for a picture of another shape.
    PoseError
        The start pose puts the model behind the camera or off-screen.
    OutOfTime
        The deadline passed; it carries the best pose the finished stages had found.
    """
    t_start = time.perf_counter()
    _check_photo(photo)
    if foreground is not None and foreground.shape != photo.shape[:2]:
        raise ValueError(f"foreground mask is {foreground.shape}, the photo {photo.shape[:2]}")
    W0, H0 = photo_size if photo_size is not None else (photo.shape[1], photo.shape[0])
    if abs(photo.shape[1] * H0 / W0 - photo.shape[0]) > 1.5:
        raise ValueError(f"a {photo.shape[1]}x{photo.shape[0]} array is not a reduced {W0}x{H0} photo")
    if init_camera is not None:
        init_camera.for_photo(W0, H0)  # a camera of another picture fails here, not stretched
    renderer = renderer if renderer is not None else Renderer()
    optimizer = optimizer if optimizer is not None else make_optimizer(options.optimizer)
    watch = None
    if deadline is not None:
        watch = Deadline(deadline, (W0, H0))
        optimizer = watch.guard(optimizer)
        progress = _checking(progress, watch)
        watch.check()

    s = min(1.0, options.pyramid.max_size / max(W0, H0))
    Wf, Hf = max(8, round(W0 * s)), max(8, round(H0 * s))
    work = resized(photo, Wf, Hf)
    fg = resized_mask(foreground.astype(bool), Wf, Hf) if foreground is not None else None
    box = parse_bbox(bbox, W0, H0) if bbox is not None else None
    sx, sy = Wf / W0, Hf / H0
    rect: Box | None = None if box is None else (box[0] * sx, box[1] * sy, box[2] * sx, box[3] * sy)

    timings: dict[str, float] = {}
    listed: list[dict[str, Any]] = []
    stage = "shading"
    sphere = options.search.pose_search == "sphere" and init_camera is None
    # The EXIF holds the focal length of the view-sphere search only: a start camera's wins.
    lens = Lens(exif, options if sphere else None)
    if sphere:
        source = "bbox" if bbox is not None else "none"
        # The search without a start camera runs without the edge term, and says so in the
        # options it reports (docs/decisions/0007-no-hint-search.md).
        options = options.replace(edge_weight=0.0)
        found, swept, stage = sphere_pose(work, model, options, renderer, optimizer, box=rect, foreground=fg,
                                          progress=progress, focal_band=lens.band, deadline=watch)
        timings["sphere"] = swept.seconds
        levels, spent, grabcut_seconds = found.levels, [found], found.grabcut_seconds
        checks = (swept.checks | fit_checks(work, model, found, None, options.color, renderer)
                  | edge_evidence(work, model, found.camera, options, renderer))
        listed = swept.listed()
        start, method = swept.ranked[0].camera, "view-sphere"
        timings["grabcut"] = grabcut_seconds
        return _result(found, levels, spent, model, options, source, method, start, checks, listed, timings,
                       W0, H0, t_start, stage, renderer, lens, rect)
    if init_camera is not None:
        source, method = "init_camera", "given"
        timings["start"] = 0.0
        start = _given_start(work, model, init_camera, rect, options)
        st = options.structure
        # Where the structure can find the pose instead, a shading fit that does not explain
        # the photo even at its coarsest level ends there (docs/decisions/0022-shading-screen.md).
        elsewhere = st.structure and (rect is not None or (fg is None and st.sphere_without_box))
        # With a box, one measure decides whether the shading explains the photo, at the fit's
        # first level and at its end: on real photos it is far above it from the first level on,
        # on renders below it. Without a box the fit may shrink onto a panel whose shading it
        # explains as a render's, and it is credible only up to ``shading_trust``
        # (docs/decisions/0022-shading-screen.md, 0041-camera-and-box-by-the-view-sphere.md).
        screen = max(st.shading_screen, st.shading_trust)
        trust = screen if rect is not None else st.shading_trust
        plan = FitPlan.hinted(options, screen=screen if elsewhere else None)
        found = fit(work, model, start, options, plan, renderer, optimizer, progress, fg, box=rect, deadline=watch)
        spent, grabcut_seconds = [found], found.grabcut_seconds
        timings["shading"] = sum(level.seconds for level in found.levels)
        if elsewhere and found.share(work, options.color) > trust:
            # The shading does not explain the photo (real paint and glass mirror their
            # surroundings): the pose is found on the photo's edges instead, by the view-sphere
            # search narrowed to the views near the start, the start refitted to the client's box
            # where there is one (docs/decisions/0020-view-sphere-search.md, 0040-a-start-says-where.md,
            # 0041-camera-and-box-by-the-view-sphere.md); with ``anchored_search``, by the
            # structure's anchored search in the box (docs/decisions/0012-structure-first.md).
            if rect is not None and st.anchored_search:
                structure = find_structure(work, model, start, rect, options, renderer, optimizer, progress)
                timings["structure"] = structure.seconds
                found, stage = structure_fit(work, model, structure, found, options, renderer), "structure"
                spent.append(found)
            else:
                near = sphere_search(work, model, model.templates(renderer), options, renderer, optimizer,
                                     init=start, progress=progress)
                timings["sphere"] = near.seconds
                found, stage = sphere_fit(work, model, near, options, renderer), "structure"
                grabcut_seconds += found.grabcut_seconds
                listed = near.listed()
                spent.append(found)
        levels = found.levels
        checks = (fit_checks(work, model, found, None, options.color, renderer)
                  | edge_evidence(work, model, found.camera, options, renderer) | {"hinted": 1.0})
    else:
        source = "bbox" if bbox is not None else "none"
        # The search without a start camera runs without the edge term, and says so in the
        # options it reports (docs/decisions/0007-no-hint-search.md).
        options = options.replace(edge_weight=0.0)
        searched = search(work, model, rect, fg, options, renderer, optimizer, progress)
        found, levels, checks, listed = searched.fit, searched.levels, searched.checks, searched.listed
        if watch is not None:
            watch.offer(found.camera, "shading")
        start, method = searched.candidate.camera, searched.candidate.source
        spent, grabcut_seconds = searched.spent, searched.grabcut_seconds
        timings.update(searched.timings)
        if (fg is None and options.search.photo_search and checks["loss"] > options.search.photo_loss
                and confidence(checks) < options.search.min_confidence):
            # Neither credible nor explained by the shading (a real photo): the pose is searched
            # on the parts' colours and the edges instead, and kept where its edges fit better
            # than the shading pose's (docs/decisions/0014-photo-search.md, 0015-one-footing.md).
            outcome = photo_pose(work, model, rect, searched.region, found, checks, options, renderer, optimizer,
                                 progress)
            listed, timings["photo_search"] = [*listed, *outcome.listed], outcome.seconds
            grabcut_seconds += outcome.grabcut_seconds
            checks = outcome.checks
            if outcome.fit is not None:
                found, stage, start, method = outcome.fit, "structure", outcome.start.camera, outcome.start.source
                levels, spent = found.levels, [*spent, found]
    timings["grabcut"] = grabcut_seconds
    return _result(found, levels, spent, model, options, source, method, start, checks, listed, timings,
                   W0, H0, t_start, stage, renderer, lens, rect)


def _checking(progress: Progress | None, watch: Deadline) -> Progress:
    """``progress`` that checks the deadline first (stages report between their searches too)."""

    def report(stage: str, evaluations: int, loss: float) -> None:
        watch.check()
        if progress is not None:
            progress(stage, evaluations, loss)

    return report


class Lens:
    """What the photo's EXIF says of the focal length, and the focal lengths (image widths) it
    lets the search reach: ``band``, within ``exif_tolerance`` of the EXIF's, for a search that
    uses it (``options`` given) when there is one and the option is on; else None."""

    def __init__(self, exif: ExifFocal | None, options: RegistrationOptions | None) -> None:
        self.exif = exif
        self.band: tuple[float, float] | None = None
        if options is not None and options.search.exif_focal and exif is not None and exif.widths is not None:
            k = options.search.exif_tolerance
            self.band = (exif.widths / k, exif.widths * k)

    def report(self, final: Camera) -> dict[str, Any]:
        """The result's ``focal``: where the focal length came from (``exif`` or ``searched``),
        the one found (pixels and image widths) and the EXIF's reading (None without EXIF)."""
        exif = self.exif
        return {"source": "exif" if self.band is not None else "searched", "pixels": final.focal,
                "widths": final.focal / final.width,
                "exif": None if exif is None or (exif.form is None and exif.warning is None and exif.focal_mm is None)
                else exif.to_dict() | {"pixels": exif.pixels(final.width)}}

    def warnings(self) -> list[str]:
        return [] if self.exif is None or self.exif.warning is None else [self.exif.warning]


def _result(found: Fit, levels: list[LevelReport], spent: list[Fit], model: VehicleModel,
            options: RegistrationOptions, source: str, method: str, start: Camera, checks: dict[str, float],
            listed: list[dict[str, Any]], timings: dict[str, float], W0: int, H0: int,
            t_start: float, stage: str, renderer: Renderer, lens: Lens, box: Box | None) -> RegistrationResult:
    """The result at the photo's own size, with its part map (:mod:`vehicle_pose.render.parts`);
    with the client's ``box`` (working-photo pixels) its checks say how well the pose agrees with
    it (``box_agreement``), in every mode."""
    if box is not None:
        checks = checks | box_agreement(found.camera, model, box)
    final = found.camera.scaled(W0, H0)
    t = time.perf_counter()
    parts = part_map(model, final, renderer)
    timings["parts"] = time.perf_counter() - t
    side = visible_side(final, model.wheels.side("left"))
    timings["optimize"] = sum(level.seconds for level in levels)
    conf = confidence(checks) if "region_iou" in checks or "edge_lead" in checks else None
    return RegistrationResult(
        camera=final,
        theta=camera_to_theta(final, model.wheels.side(side), side),
        loss=levels[-1].loss,
        evaluations=sum(level.evaluations for f in spent for level in f.levels),
        restarts=sum(level.restarts for f in spent for level in f.levels),
        seconds=time.perf_counter() - t_start,
        model=model,
        start_source=source,
        start_camera=start.scaled(W0, H0),
        levels=levels,
        options=options,
        foreground=resized_mask(found.foreground, W0, H0),
        timings=timings,
        start_method=method,
        confidence=conf,
        failed=conf is not None and conf < options.search.min_confidence,
        checks=checks,
        candidates=listed,
        pose_stage=stage,
        parts=parts,
        focal=lens.report(final),
        warnings=lens.warnings(),
    )
