"""The search without a start camera (``docs/decisions/0007-no-hint-search.md``).

Find the vehicle's region (GrabCut from the client's box or from rectangles inside the photo's
border), gather start poses (a view search and matched wheel ellipses), screen the best
distinct ones on a reduced window of the photo, refine the best few one level up, and polish
the best of those at working size.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from vehicle_pose.errors import PoseError
from vehicle_pose.geometry.camera import Camera
from vehicle_pose.geometry.window import Window
from vehicle_pose.metrics import rotation_error
from vehicle_pose.model.library import VehicleModel
from vehicle_pose.registration.credibility import confidence, fit_checks
from vehicle_pose.registration.fit import Fit, FitPlan, Progress, fit
from vehicle_pose.registration.options import RegistrationOptions
from vehicle_pose.registration.result import LevelReport
from vehicle_pose.registration.segmentation import resegment
from vehicle_pose.render.renderer import Renderer
from vehicle_pose.search.optimize import Optimizer, make_optimizer
from vehicle_pose.search.views import (
    Box,
    Candidate,
    box_union,
    distinct,
    refocus,
    score_cameras,
    view_camera,
    view_search,
)
from vehicle_pose.search.wheels import detect_wheels, wheel_candidates
from vehicle_pose.segment.region import VehicleRegion, find_vehicle

__all__ = ["SearchPass", "search", "search_pass", "search_starts"]


@dataclass
class SearchPass:
    """One search without a start camera: the winning fit and how it was found.

    ``spent`` holds every fit run (for the evaluation count), ``listed`` the screened starts
    as the result reports them, ``checks`` the margin over alternatives and the agreement.
    """

    fit: Fit
    levels: list[LevelReport]
    candidate: Candidate
    region: VehicleRegion
    checks: dict[str, float]
    listed: list[dict[str, Any]]
    spent: list[Fit]
    grabcut_seconds: float
    timings: dict[str, float]


def _window_margin(options: RegistrationOptions) -> float | None:
    """The start searches' window margin; the theta coordinates need the whole image (their
    principal point is its centre)."""
    return options.search.window_margin if options.parametrization == "view" else None


def _projected_box(model: VehicleModel, camera: Camera) -> Box | None:
    """The box of the model's projection, None when part of it is behind the camera."""
    uv = camera.project(model.mesh.extreme_points(600))
    if not np.all(np.isfinite(uv)):
        return None
    return float(uv[:, 0].min()), float(uv[:, 1].min()), float(uv[:, 0].max()), float(uv[:, 1].max())


def search_starts(
    work: npt.NDArray[np.uint8],
    model: VehicleModel,
    rect: Box | None,
    fg: npt.NDArray[np.bool_] | None,
    region: VehicleRegion | None,
    options: RegistrationOptions,
    renderer: Renderer,
) -> tuple[list[Candidate], VehicleRegion]:
    """The vehicle's region (``region`` when given) and the start poses to screen, best first."""
    Hf, Wf = work.shape[:2]
    search = options.search
    lod_faces = min(4096, options.pyramid.min_faces)
    if region is not None:
        regions = [region]
    elif fg is not None:
        regions = [VehicleRegion.from_mask(fg)]
    elif rect is not None:
        regions = [find_vehicle(work, rect=rect)]
    else:
        regions = [find_vehicle(work, border=search.region_borders[0])]
    # The region hypothesis whose best view fits it best wins; narrower start rectangles are
    # tried only when the first region is not already well explained by a view.
    margin = _window_margin(options)
    searched = [(view_search(work, reg, model, renderer, max_faces=lod_faces, margin=margin), reg) for reg in regions]
    if region is None and fg is None and rect is None and searched[0][0][0].score > search.region_fit:
        for border in search.region_borders[1:]:
            reg = find_vehicle(work, border=border)
            searched.append((view_search(work, reg, model, renderer, max_faces=lod_faces, margin=margin), reg))
    cands, found = min(searched, key=lambda e: e[0][0].score)
    if search.wheels:
        ellipses = detect_wheels(work, found, max_count=4)
        pairs = wheel_candidates(ellipses, model, Wf, Hf)
        cands += score_cameras(work, found, model, pairs, renderer, max_faces=lod_faces, margin=margin)
    starts = distinct(cands, search.starts)
    best = starts[0]
    if best.source == "view-search":
        # Front and back (and left and right from behind) are the commonest confusion: the
        # best view's twin half a turn away is always screened.
        d = best.detail
        twin = view_camera(model, d["azimuth"] + 180.0, d["elevation"], -d["roll"], found.box, Wf, Hf,
                           best.camera.focal)
        if all(rotation_error(twin.R, c.camera.R) >= 25.0 for c in starts):
            starts.append(Candidate(twin, "view-search", detail={**d, "azimuth": (d["azimuth"] + 180.0) % 360,
                                                                 "roll": -d["roll"], "twin": 1.0}))
    starts += [
        replace(starts[0], camera=refocus(starts[0].camera, f * Wf, model, found.box),
                detail={**starts[0].detail, "focal_widths": f})
        for f in search.start_focals
    ]
    return starts, found


def search_pass(
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
) -> SearchPass:
    """Find the vehicle's region (unless given), search start poses, screen them on a reduced
    photo, refine the best distinct ones and the best of those at working size."""
    Hf, Wf = work.shape[:2]
    budgets = options.budgets
    timings: dict[str, float] = {}
    listed: list[dict[str, Any]] = []
    spent: list[Fit] = []
    grabcut_seconds = 0.0
    t = time.perf_counter()
    if progress is not None:
        progress(f"{stage}finding the vehicle", 0, float("nan"))
    starts, region = search_starts(work, model, rect, fg, given_region, options, renderer)
    timings["start"] = time.perf_counter() - t

    # Screen every start on a reduced photo, then refine the best distinct ones.
    window = Window.around(region.box, Wf, Hf, size=options.search.screen_size, margin=_window_margin(options))
    small = window.image(work)
    screen = FitPlan(coarse_to_fine=False, evaluations=budgets.screen_evaluations, resegment=False, edge_weight=0.0)
    screened: list[tuple[float, Camera, Candidate]] = []
    for k, cand in enumerate(starts):
        try:
            sf = fit(small, model, window.camera(cand.camera), options, screen, renderer, optimizer, progress,
                     None if fg is None else window.mask(fg), f"{stage}start {k + 1}/{len(starts)}: ")
        except PoseError:
            continue
        grabcut_seconds += sf.grabcut_seconds
        spent.append(sf)
        screened.append((sf.objective, window.full_camera(sf.camera), cand))
        listed.append(cand.to_dict() | {"screened_loss": sf.objective})
    if not screened:
        raise PoseError("no start pose puts the model in view of the photo")
    screened.sort(key=lambda e: e[0])
    timings["screen"] = time.perf_counter() - t - timings["start"]
    chosen: list[tuple[float, Camera, Candidate]] = []
    for entry in screened:
        if all(rotation_error(entry[1].R, c[1].R) >= 10.0 for c in chosen):
            chosen.append(entry)
        if len(chosen) == options.search.refine:
            break
    # Refine the chosen poses one level up (on a window around each), then the best of
    # them at working size.
    longer = max(Wf, Hf)
    mids = [c for c in options.pyramid.coarse_sizes if options.search.screen_size < c < 0.75 * longer]
    fits = []
    refiner = make_optimizer(options.search.refine_optimizer)
    refine = FitPlan(coarse_to_fine=False, evaluations=budgets.refine_evaluations, resegment=False, edge_weight=0.0)
    for k, (_, cam, cand) in enumerate(chosen):
        prefix = stage + (f"refine {k + 1}/{len(chosen)}: " if len(chosen) > 1 else "refine: ")
        win = Window.around(box_union(region.box, _projected_box(model, cam)), Wf, Hf,
                            size=mids[-1] if mids else longer, margin=_window_margin(options))
        mf = fit(win.image(work), model, win.camera(cam), options, refine, renderer, refiner, progress,
                 None if fg is None else win.mask(fg), prefix)
        spent.append(mf)
        grabcut_seconds += mf.grabcut_seconds
        fits.append((Fit(win.full_camera(mf.camera), mf.levels, win.full_mask(mf.foreground), 0.0), cand))
    best_mid, best_cand = min(fits, key=lambda e: e[0].objective)
    if mids:
        t = time.perf_counter()
        if fg is not None:
            final_fg = fg
        elif not options.segmentation.grabcut:
            final_fg = np.ones((Hf, Wf), bool)
        else:
            # Segmented again at working size, seeded by the refined pose (as between levels).
            again = resegment(work, model, best_mid.camera, options.segmentation, renderer, None, max(Wf, Hf))
            final_fg = best_mid.foreground if again is None else again
        grabcut_seconds += time.perf_counter() - t
        # The final level polishes a pose within a pixel or two, as the finest level of the
        # hinted chain does, with its budget.
        final = FitPlan(coarse_to_fine=False, evaluations=budgets.fine_evaluations, resegment=False, edge_weight=0.0,
                        step_scale=0.4)
        polished = fit(work, model, best_mid.camera, options, final, renderer, optimizer, progress, final_fg,
                       f"{stage}final: ")
        spent.append(polished)
        levels = [*best_mid.levels, *polished.levels]
    else:
        polished = best_mid
        levels = polished.levels

    # Credibility: the margin over alternatives (refined, else screened); agreement reported.
    won = next(e for e in screened if e[2] is best_cand)
    others = [e[0] for e in screened if rotation_error(e[1].R, polished.camera.R) >= 15.0]
    near = [e for e in screened if e is not won and "focal_widths" not in e[2].detail
            and rotation_error(e[1].R, polished.camera.R) < 15.0]
    rivals = [f.objective for f, _ in fits if rotation_error(f.camera.R, best_mid.camera.R) >= 15.0]
    plain = [e for e in screened if "focal_widths" not in e[2].detail]
    checks = {
        "margin": (
            (min(rivals) - best_mid.objective) / max(min(rivals), 1e-9) if rivals
            else (min(others) - won[0]) / max(min(others), 1e-9) if others else 1.0
        ),
        "agreement": len(near) / max(1, len(plain) - 1),
    }
    return SearchPass(polished, levels, best_cand, region, checks, listed, spent, grabcut_seconds, timings)


def search(
    work: npt.NDArray[np.uint8],
    model: VehicleModel,
    rect: Box | None,
    fg: npt.NDArray[np.bool_] | None,
    options: RegistrationOptions,
    renderer: Renderer,
    optimizer: Optimizer,
    progress: Progress | None,
) -> SearchPass:
    """One search pass, judged (``checks``); when its pose is not credible, a second pass in the
    foreground segmented around that pose, usually closer to the vehicle than the region found
    with no pose at all, and the lower loss wins. The region check stays against the first
    region, found before any pose was known."""
    first = search_pass(work, model, rect, fg, None, options, renderer, optimizer, progress)
    checks = first.checks | fit_checks(work, model, first.fit, first.region, options.color, renderer)
    result = replace(first, checks=checks)
    if fg is None and options.search.second_pass and confidence(checks) < options.search.min_confidence:
        t = time.perf_counter()
        again = search_pass(work, model, rect, fg, VehicleRegion.from_mask(first.fit.foreground), options,
                            renderer, optimizer, progress, "second pass: ")
        if again.fit.objective < first.fit.objective:
            checks = again.checks | fit_checks(work, model, again.fit, first.region, options.color, renderer)
            result = replace(again, region=first.region, checks=checks)
        result = replace(result, spent=[*first.spent, *again.spent],
                         grabcut_seconds=first.grabcut_seconds + again.grabcut_seconds,
                         timings={**first.timings, "second_pass": time.perf_counter() - t},
                         checks={**result.checks, "passes": 2.0})
    return result
