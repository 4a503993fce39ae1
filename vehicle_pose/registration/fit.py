"""One fit: a coarse-to-fine search from one start camera on the working photo (method.md §5).

Each level renders a level of detail of the model at a reduced photo and minimises the loss
(plus the edge and box terms) over the search coordinates; between levels GrabCut runs again,
seeded by the pose found; from a start camera the first level runs an evolution strategy beside
the simplex (``docs/decisions/0025-spread-first-level.md``), and the second level also probes
dolly zooms of the first level's pose and the first level's runner-up
(``docs/decisions/0005-perspective-probes.md``). What a fit runs (levels, budget, terms) is a
:class:`FitPlan`, chosen by the stage that calls it.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from vehicle_pose.errors import CameraError, PoseError
from vehicle_pose.geometry.camera import Camera
from vehicle_pose.geometry.parametrize import Parametrization, SearchFrame, ViewParams, make_parametrization
from vehicle_pose.geometry.pose import Side, visible_side
from vehicle_pose.loss.alternatives import make_loss
from vehicle_pose.loss.edges import EdgeLoss
from vehicle_pose.loss.invariant import make_target
from vehicle_pose.model.library import VehicleModel
from vehicle_pose.model.mesh import Mesh
from vehicle_pose.photo import is_gray, resized, resized_mask
from vehicle_pose.registration.deadline import Deadline
from vehicle_pose.registration.options import Pyramid, RegistrationOptions
from vehicle_pose.registration.result import LevelReport
from vehicle_pose.registration.segmentation import box_mask, doubt_weights, first_foreground, resegment, silhouette
from vehicle_pose.render.renderer import Frame, Renderer
from vehicle_pose.search.optimize import CMAES, Batch, Optimizer, OptimizeResult
from vehicle_pose.search.views import Box, box_overflow

__all__ = ["Progress", "FitPlan", "Fit", "fit", "level_sizes", "face_budget", "probe_factors", "search_frame",
           "loss_share"]

Progress = Callable[[str, int, float], None]
"""``progress(stage, evaluations, loss)``, called every 20 evaluations and after each level."""

_INVALID = 10.0  # the objective of coordinates that give no camera
# How far a phone's EXIF focal length is from the lens's, as a log: the 35 mm equivalent's
# width and diagonal conventions 4 % apart on a 4:3 sensor, then rounded to a millimetre (2 % at
# 24 mm); the scale of the prior of ``FitPlan.focal_prior``.
EXIF_SPREAD = 0.03


class _Screened(Exception):
    """Raised by a first level's objective whose best pose is still above the plan's screen;
    ``luminance``: that pose's luminance share, where the fit judges a colour loss by it."""

    def __init__(self, luminance: float | None) -> None:
        super().__init__()
        self.luminance = luminance


@dataclass(frozen=True)
class FitPlan:
    """What one fit runs.

    ``coarse_to_fine``: the pyramid's coarse levels before the working size (else one level);
    ``evaluations``: the budget of each level but the last of several; ``resegment``: GrabCut
    again between levels; ``edge_weight``: the edge term's weight (0: none); ``step_scale``
    scales the first level's simplex; ``focal_band``: the focal lengths (image widths, low and
    high) the fit may reach (a lens known from the photo's EXIF), None for any; with a band the
    perspective probes do not run; ``screen``: the loss over its maximum (:func:`loss_share`)
    above which the fit ends after its first level, where the shading does not explain the
    photo even coarsely and the caller has another way to the pose, None to run every level;
    ``screen_after``: with a screen, the first level's evaluations after which a pose still
    above it ends the fit there (0: only at the level's end); ``focal_prior``: with a band, the
    weight of the band's middle as a prior in one more run of the last level with the focal
    length free (``exif_refine``), kept where its objective is lower (0: none).
    """

    coarse_to_fine: bool
    evaluations: int
    resegment: bool
    edge_weight: float
    step_scale: float = 1.0
    focal_band: tuple[float, float] | None = None
    screen: float | None = None
    spread: int = 0
    screen_after: int = 0
    focal_prior: float = 0.0

    @classmethod
    def hinted(cls, options: RegistrationOptions, screen: float | None = None) -> FitPlan:
        """The registration from a client's start camera: every option as given."""
        seg = options.segmentation
        return cls(options.pyramid.coarse_to_fine, options.budgets.max_evaluations, seg.grabcut and seg.resegment,
                   options.terms.edge_weight, screen=screen, spread=options.budgets.spread_evaluations,
                   screen_after=options.structure.screen_after)

    @property
    def prior_lens(self) -> float | None:
        """The focal length (image widths) the last level's free run is priced about: the band's
        geometric middle, where the plan has a band and a ``focal_prior``; else None."""
        if self.focal_band is None or self.focal_prior <= 0:
            return None
        return float(np.sqrt(self.focal_band[0] * self.focal_band[1]))

    def screens(self, share: float) -> bool:
        """Whether a first level ending at ``share`` (its loss over the loss's maximum, on the
        luminance: :meth:`Fit.share`) ends the fit (above the ``screen``)."""
        return self.screen is not None and share > self.screen


@dataclass
class Fit:
    """One fit's pose (at working size), its levels, and the foreground it ended on;
    ``screened``: the fit ended after its first level, its plan's ``screen`` passed."""

    camera: Camera
    levels: list[LevelReport]
    foreground: npt.NDArray[np.bool_]
    grabcut_seconds: float
    screened: bool = False

    @property
    def loss(self) -> float:
        return self.levels[-1].loss

    @property
    def objective(self) -> float:
        return self.levels[-1].objective

    def share(self, work: npt.NDArray[np.uint8], color: bool) -> float:
        """How far the shading is from explaining the photo: the final loss over its maximum,
        on the photo's luminance. The thresholds that judge it (``shading_screen``,
        ``shading_trust``, ``shading_polish``) are set on the luminance loss; a colour loss
        (``color``) also counts the photo's chroma, which on a grey or single-coloured car is
        noise that no pose explains (on renders the colour loss over its maximum ends at
        0.43-0.67 within a pixel of the truth, the luminance loss at 0.002-0.013), so the
        luminance's is taken where the level has one
        (``docs/decisions/0069-a-colour-loss-judged-on-the-luminance.md``)."""
        last = self.levels[-1]
        return last.luminance if last.luminance is not None else loss_share(last.loss, work, color)


def loss_share(loss: float, work: npt.NDArray[np.uint8], color: bool) -> float:
    """A loss over the loss's maximum: 3 for a colour loss on a colour photo, else 1."""
    return loss / (3.0 if color and not is_gray(work) else 1.0)


def level_sizes(width: int, height: int, pyramid: Pyramid, coarse_to_fine: bool) -> list[tuple[int, int]]:
    """Image sizes of the levels, coarsest first, ending with ``width`` x ``height``."""
    longer = max(width, height)
    sizes = []
    if coarse_to_fine:
        for size in pyramid.coarse_sizes:
            if size < 0.75 * longer:
                s = size / longer
                sizes.append((max(8, round(width * s)), max(8, round(height * s))))
    return [*sizes, (width, height)]


def face_budget(pixels: float, pyramid: Pyramid) -> int:
    """Faces of the level of detail for a silhouette of ``pixels`` pixels."""
    wanted = max(float(pyramid.min_faces), pyramid.faces_per_pixel * pixels)
    return int(2 ** np.ceil(np.log2(wanted)))


def probe_factors(camera: Camera, options: RegistrationOptions) -> list[float]:
    """Focal factors of the perspective probes: ``focal_starts``, and when the focal length is
    outside ``focal_range`` (image widths) one more to the range's geometric middle."""
    factors = list(options.probes.focal_starts)
    lo, hi = (r * camera.width for r in options.probes.focal_range)
    if not lo <= camera.focal <= hi:
        factors.append(float(np.sqrt(lo * hi)) / camera.focal)
    return factors


def _screened_out(plan: FitPlan, run: tuple[OptimizeResult, Parametrization], share_of: Callable[[Frame], float],
                  renderer: Renderer, mesh: Mesh) -> bool:
    """Whether ``run``'s pose is above the plan's screen (the fit will end there); renders it
    only where the plan has a screen."""
    if plan.screen is None:
        return False
    res, params = run
    return plan.screens(share_of(renderer.render(mesh, params.camera(res.x))))


def search_frame(model: VehicleModel, side: Side, pivot: float,
                 focal_band: tuple[float, float] | None = None) -> SearchFrame:
    """What the search coordinates know of ``model`` seen from ``side``."""
    centre, radius = model.mesh.sphere
    return SearchFrame(centre, radius, model.wheels.side(side), side, pivot, focal_band)


def fit(
    work: npt.NDArray[np.uint8],
    model: VehicleModel,
    start: Camera,
    options: RegistrationOptions,
    plan: FitPlan,
    renderer: Renderer,
    optimizer: Optimizer,
    progress: Progress | None = None,
    foreground: npt.NDArray[np.bool_] | None = None,
    stage_prefix: str = "",
    *,
    box: Box | None = None,
    deadline: Deadline | None = None,
) -> Fit:
    """Register from one start camera on ``work`` (already at working size).

    ``foreground`` (working size) replaces GrabCut. ``box`` (working-size pixels), the client's
    box of the vehicle, widens what GrabCut may call foreground beyond the grown start
    silhouette, and adds the box term. ``deadline`` is offered each level's pose.
    """
    Hf, Wf = work.shape[:2]
    start = start.scaled(Wf, Hf)
    side: Side
    if options.side in ("left", "right"):
        side = "left" if options.side == "left" else "right"
    else:
        side = visible_side(start, model.wheels.side("left"))
    frame = search_frame(model, side, options.probes.dolly_pivot, plan.focal_band)

    seed = silhouette(model, start, renderer)
    if seed.sum() < 16:
        raise PoseError("the start pose puts the model off-screen or behind the camera")

    t = time.perf_counter()
    segment_again = plan.resegment and foreground is None
    region = None if box is None else box_mask(box, Wf, Hf, options.segmentation.box_margin)
    if foreground is not None:
        foreground = resized_mask(foreground, Wf, Hf)
    else:
        foreground = first_foreground(work, seed, options.segmentation, region)
    grabcut_seconds = time.perf_counter() - t

    terms, budgets = options.terms, options.budgets
    colour = options.color and not is_gray(work)
    camera = start
    levels: list[LevelReport] = []
    # The box term's points, sampled once per fit and only when the term is on (the no-hint
    # chain runs a fit per screened start, without a box).
    box_points = model.mesh.extreme_points(600) if box is not None and terms.box_weight > 0 else None
    area = max(float(seed.sum()), 1.0)
    max_pixels = options.pyramid.max_pixels
    fine = min(1.0, float(np.sqrt(max_pixels / area))) if max_pixels > 0 else 1.0
    sizes = level_sizes(max(8, round(Wf * fine)), max(8, round(Hf * fine)), options.pyramid, plan.coarse_to_fine)
    runner_up: Camera | None = None
    for li, (w, h) in enumerate(sizes):
        t = time.perf_counter()
        # Faces hidden from every outside view (the cabin of many CAD cars) are dropped: they
        # never reach a pixel but cost the rasteriser as much as visible ones.
        mesh = model.exterior(face_budget(float(seed.sum()) * (w * h) / (Wf * Hf), options.pyramid), renderer)
        level_fg = resized_mask(foreground, w, h)
        level_work = resized(work, w, h)
        weights = doubt_weights(level_fg, region, options.segmentation.doubt_weight)
        target = make_target(level_work, level_fg, color=options.color, weights=weights)
        loss_fn = make_loss(options.loss, target)
        # A colour loss is judged on the luminance (Fit.share): the same loss on the gray photo.
        luma_fn = make_loss(options.loss, make_target(level_work, level_fg, color=False, weights=weights)) \
            if colour else None

        def share_of(rendered: Frame) -> float:
            if luma_fn is not None:
                return float(luma_fn(rendered))
            return loss_share(float(loss_fn(rendered)), work, options.color)
        edge_fn = None
        if plan.edge_weight > 0:
            edge_fn = EdgeLoss(resized(work, w, h), foreground=target.foreground, crease=terms.edge_crease)
        stage = f"{stage_prefix}level {li + 1}/{len(sizes)} ({w}x{h})"
        level_box = None
        if box is not None and box_points is not None:
            level_box = (box[0] * w / Wf, box[1] * h / Hf, box[2] * w / Wf, box[3] * h / Hf)
        counter = [0]
        # With a screen, the first level's best pose so far (its objective, loss and camera):
        # still above the screen after ``screen_after`` evaluations, it ends the fit there.
        screening = li == 0 and plan.screen is not None and plan.screen_after > 0
        lowest: list[tuple[float, float, Camera]] = []

        def search(reference: Camera, budget: int, how: Optimizer = optimizer,
                   lens: float | None = None) -> tuple[OptimizeResult, Parametrization]:
            # ``lens`` (image widths): the focal length free, priced by the prior about it.
            within = frame if lens is None else replace(frame, focal_band=None)
            params = make_parametrization(options.parametrization, reference.scaled(w, h), within)
            try:
                x0 = params.start()
            except PoseError:
                raise PoseError(f"the start pose does not show the {side} side's wheels") from None

            def camera_at(x: npt.NDArray[np.float64]) -> Camera | None:
                try:
                    return params.camera(x)
                except (PoseError, CameraError):
                    return None

            def score(cam: Camera, rendered: Frame) -> float:
                shading = float(loss_fn(rendered))
                value = shading
                if lens is not None:
                    value += plan.focal_prior * float(np.log(cam.focal / (lens * cam.width)) / EXIF_SPREAD) ** 2
                if edge_fn is not None:
                    value += plan.edge_weight * edge_fn(rendered)
                if level_box is not None and box_points is not None:
                    value += terms.box_weight * box_overflow(cam, box_points, level_box, terms.box_tolerance,
                                                             terms.box_shortfall)
                counter[0] += 1
                if progress is not None and counter[0] % 20 == 0:
                    progress(stage, counter[0], value)
                if screening:
                    if not lowest or value < lowest[0][0]:
                        lowest[:] = [(value, shading, cam)]
                    if counter[0] == plan.screen_after:
                        luminance = share_of(renderer.render(mesh, lowest[0][2])) if colour else None
                        if plan.screens(luminance if luminance is not None
                                        else loss_share(lowest[0][1], work, options.color)):
                            raise _Screened(luminance)
                return value

            def objective(x: npt.NDArray[np.float64]) -> float:
                cam = camera_at(x)
                return _INVALID if cam is None else score(cam, renderer.render(mesh, cam))

            def objective_many(xs: npt.NDArray[np.float64]) -> list[float]:
                # A generation's poses drawn together (Renderer.render_many), scored in order.
                cams = [camera_at(x) for x in xs]
                frames = iter(renderer.render_many(mesh, [c for c in cams if c is not None]))
                return [_INVALID if c is None else score(c, next(frames)) for c in cams]

            steps = params.steps() * plan.step_scale * 0.4**li
            return how(Batch(objective, objective_many), x0, steps, max_evaluations=budget), params

        budget = budgets.fine_evaluations if li == len(sizes) - 1 and li > 0 else plan.evaluations
        try:
            runs = [search(camera, budget)]
        except _Screened as screened:
            # Still far from explaining the photo after a quarter of the level: no photo of the
            # benchmarks came under the screen from there (docs/decisions/0027-screen-within-
            # the-first-level.md), and the caller has another way to the pose.
            objective_value, shading, best = lowest[0]
            camera = best.scaled(Wf, Hf)
            levels.append(LevelReport(w, h, mesh.n_faces, counter[0], 0, shading, time.perf_counter() - t,
                                      objective_value, screened.luminance))
            if deadline is not None:
                deadline.offer(camera, "shading")
            if progress is not None:
                progress(stage, counter[0], objective_value)
            return Fit(camera, levels, foreground, grabcut_seconds, screened=True)
        if li == 0 and plan.spread > 0 and len(sizes) > 1 and plan.focal_band is None and not _screened_out(
                plan, runs[0], share_of, renderer, mesh):
            # A rough start (5-15 degrees, the focal length a third off) can lie beyond the
            # simplex's basin, most of all where the frame cuts the car: an evolution strategy
            # spread about as far as the start may be off searches beside it, where evaluations
            # are cheapest. The first level's objective is too coarse to choose between the two
            # (docs/decisions/0025-spread-first-level.md): the loser is probed at the second.
            spread: Optimizer = CMAES(sigma=options.probes.start_spread)
            runs.append(search(camera, plan.spread, spread if deadline is None else deadline.guard(spread)))
        starts: list[Camera] = []
        if li == 1 and plan.focal_band is None:
            # The second level also probes dolly zooms of the first level's pose, on the same
            # mask (the perspective is what a simplex corrects least), and the first level's
            # runner-up; a probe that beats the main search is searched on.
            if options.probes.focal_starts:
                view = ViewParams.about(camera, frame)
                starts = [view.dolly_zoom(f) for f in probe_factors(camera, options)]
            starts += [runner_up] if runner_up is not None else []
        if starts:
            probes = [search(start, budgets.focal_evaluations) for start in starts]
            best_probe = min(probes, key=lambda e: e[0].fun)
            runs += probes
            if best_probe[0].fun < runs[0][0].fun * (1.0 + options.probes.probe_margin):
                runs.append(search(best_probe[1].camera(best_probe[0].x).scaled(Wf, Hf),
                                   plan.evaluations - budgets.focal_evaluations))
        if li == len(sizes) - 1 and plan.prior_lens is not None:
            # The focal length held at the EXIF's is a phone's rounding and convention off (2 %
            # at the median); where the shading pins it closer, a last run with it free finds
            # it, the EXIF's prior keeping it from walking the focal-depth valley.
            held, held_params = min(runs, key=lambda e: e[0].fun)
            runs.append(search(held_params.camera(held.x).scaled(Wf, Hf), budget, lens=plan.prior_lens))
        res, params = min(runs, key=lambda e: e[0].fun)
        if li == 0 and len(runs) > 1:
            other, other_params = max(runs, key=lambda e: e[0].fun)
            runner_up = other_params.camera(other.x).scaled(Wf, Hf)
        if len(runs) > 1:
            res = replace(res, evaluations=sum(r.evaluations for r, _ in runs),
                          restarts=sum(r.restarts for r, _ in runs))
        camera = params.camera(res.x).scaled(Wf, Hf)
        loss = res.fun
        # The objective is the loss alone unless other terms join it; then the pose is drawn
        # once more for its loss, and with a colour loss for its luminance: one draw for both.
        rescored = edge_fn is not None or level_box is not None or plan.prior_lens is not None
        final = renderer.render(mesh, camera.scaled(w, h)) if rescored or colour else None
        if rescored and final is not None:
            loss = float(loss_fn(final))
        luminance = share_of(final) if colour and final is not None else None
        levels.append(LevelReport(w, h, mesh.n_faces, res.evaluations, res.restarts, loss, time.perf_counter() - t,
                                  res.fun, luminance))
        if deadline is not None:
            deadline.offer(camera, "shading")
        if progress is not None:
            progress(stage, res.evaluations, res.fun)
        if li == 0 and len(sizes) > 1 and plan.screens(
                luminance if luminance is not None else loss_share(loss, work, options.color)):
            return Fit(camera, levels, foreground, grabcut_seconds, screened=True)
        if segment_again and li < len(sizes) - 1:
            t = time.perf_counter()
            # At the next level's resolution: a mask upsampled from a coarser GrabCut
            # misplaces the outline by a pixel, and the pose follows the mask.
            again = resegment(work, model, camera, options.segmentation, renderer, region, max(sizes[li + 1]))
            foreground = foreground if again is None else again
            grabcut_seconds += time.perf_counter() - t
    return Fit(camera, levels, foreground, grabcut_seconds)
