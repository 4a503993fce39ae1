"""The structure's pose: with a start camera and the vehicle's box, where the shading fit's loss
does not explain the photo, the pose is found on the photo's edges and the box instead
(``docs/decisions/0012-structure-first.md``).

On real photos the invariant loss explains little of a car (sky and buildings mirrored in the
paint and the glass), and the loss with a GrabCut mask pulls the model onto the bright panels,
shrunk inside the car. What stays put on a real photo is its structure: the outline, the
window frames, the lights and the wheel arches, and the box the client drew. So:

1. **Anchored search**: the rotation and the focal length are searched with the place and the
   size tied to the box (each camera moved and scaled until the model's projection, cut to the
   photo, fills the box: :func:`~vehicle_pose.search.views.fit_to_box`), scoring the directional
   chamfer of the model's edges against the photo's (:class:`~vehicle_pose.loss.edges.EdgeLoss`).
   Four coordinates instead of seven, and none of them can shrink the model onto a panel.
   The chamfer of a real photo has a broad floor about the true rotation, pitted with local
   minima a few degrees apart (every reflection makes an edge), so the search is the
   cross-entropy method (:class:`~vehicle_pose.search.optimize.CrossEntropy`), which returns
   the mean of the best samples rather than one pit; and the means of independent searches
   are averaged, since each still leans towards a pit of its own.
2. **Free refinement**: all seven view coordinates, on the chamfer plus the box term
   (:func:`~vehicle_pose.search.views.box_overflow`), so that a loose or tight box does not fix
   the size.

Both run from the client's start (refitted to the box), not from the shading fit's pose, which
on a real photo has already shrunk onto a panel. Where the loss does explain the photo (its
value over its maximum at most ``shading_screen`` with the box: on real photos it is far above
it from the first level on, on renders below it), the shading fit stays the result: it is the
more precise.
By default the pose is found by the view-sphere search narrowed to the start instead
(``docs/decisions/0041-camera-and-box-by-the-view-sphere.md``); this module's anchored search
runs with ``structure.anchored_search``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from functools import cached_property

import cv2
import numpy as np
import numpy.typing as npt

from vehicle_pose.errors import CameraError, PoseError
from vehicle_pose.geometry.camera import Camera
from vehicle_pose.geometry.parametrize import ViewParams
from vehicle_pose.loss.alternatives import make_loss
from vehicle_pose.loss.edges import EdgeLoss
from vehicle_pose.loss.invariant import make_target
from vehicle_pose.model.library import VehicleModel
from vehicle_pose.model.mesh import Mesh
from vehicle_pose.photo import is_gray, resized, resized_mask
from vehicle_pose.registration.fit import Fit, Progress, face_budget
from vehicle_pose.registration.options import RegistrationOptions
from vehicle_pose.registration.result import LevelReport
from vehicle_pose.registration.segmentation import silhouette
from vehicle_pose.render.renderer import Frame, Renderer
from vehicle_pose.search.optimize import Batch, CrossEntropy, Optimizer, OptimizeResult
from vehicle_pose.search.views import Box, box_overflow, fit_to_box

__all__ = [
    "BoxAnchoredParams", "EdgeFit", "Structure", "StructureCost", "find_structure", "structure_fit", "loss_at",
    "losses_at",
]

FloatArray = npt.NDArray[np.float64]

_INVALID = 10.0  # the objective of coordinates that give no camera
_POINTS = 1000  # surface points whose projection is fitted to the box


@dataclass(frozen=True)
class BoxAnchoredParams:
    """Rotation vector and log focal length about a reference, the place and size fitted to a box.

    ``x = (r, g)``: the reference's rotation turned by the rotation vector ``r`` (radians, in
    camera coordinates), its focal length times ``exp(g)``; the camera is then moved along and
    across its axis until ``points`` project, cut to the image, onto ``box``.
    """

    reference: Camera
    box: Box
    points: FloatArray
    centre: FloatArray

    def start(self) -> FloatArray:
        return np.zeros(4)

    @cached_property
    def _depth(self) -> float:
        """The reference's depth of the model centre (mesh units), kept as the fit's first guess."""
        return float(self.reference.to_camera(self.centre[None])[0, 2])

    def camera(self, x: FloatArray) -> Camera:
        ref = self.reference
        if not np.all(np.isfinite(x)) or abs(float(x[3])) > 5.0:
            raise PoseError("focal length out of range")
        K = ref.K.copy()
        K[0, 0] *= float(np.exp(x[3]))
        K[1, 1] *= float(np.exp(x[3]))
        R = cv2.Rodrigues(np.asarray(x[:3], dtype=np.float64))[0] @ ref.R
        depth = max(self._depth, 1e-6) * float(np.exp(x[3]))
        turned = Camera(K, R, np.array([0.0, 0.0, depth]) - R @ self.centre, ref.width, ref.height)
        return fit_to_box(turned, self.points, self.centre, self.box, rounds=4, clip=True)


@dataclass
class Structure:
    """Each structure stage's report and pose (at working size); the last pose is the result."""

    levels: list[LevelReport]
    cameras: list[Camera]
    seconds: float

    @property
    def camera(self) -> Camera:
        return self.cameras[-1]


def _search(optimizer: Optimizer, objective: StructureCost, params: BoxAnchoredParams | ViewParams, x0: FloatArray,
            steps: FloatArray, budget: int) -> OptimizeResult:
    def camera(x: FloatArray) -> Camera | None:
        try:
            return params.camera(x)
        except (PoseError, CameraError):
            return None

    def one(x: FloatArray) -> float:
        cam = camera(x)
        return _INVALID if cam is None else objective(cam)

    # A population's poses are drawn together (Renderer.render_many), the values the same.
    return optimizer(Batch(one, lambda xs: objective.many([camera(x) for x in xs])), x0, steps,
                     max_evaluations=budget)


class StructureCost:
    """The chamfer of ``mesh``'s edges against the photo's (truncated at ``tau`` of the diagonal,
    creases as ``options.terms`` says), plus ``box_weight`` times the box term of ``points``
    when a ``box`` is given; called with a camera for the photo's size, or with many
    (:meth:`many`). ``progress`` is told every 20 poses scored, as ``stage``."""

    def __init__(self, image: npt.NDArray[np.uint8], mesh: Mesh, renderer: Renderer, options: RegistrationOptions,
                 *, tau: float, box: Box | None = None, points: FloatArray | None = None,
                 progress: Progress | None = None, stage: str = "") -> None:
        if box is not None and points is None:
            raise ValueError("the box term needs the model's points")
        self.edges = EdgeLoss(image, tau=tau, crease=options.terms.edge_crease)
        self.mesh, self.renderer, self.box, self.box_points = mesh, renderer, box, points
        self.terms = options.terms
        self.progress, self.stage, self.count = progress, stage, 0

    def __call__(self, cam: Camera) -> float:
        return self._score(cam, self.renderer.render(self.mesh, cam))

    def many(self, cameras: list[Camera | None]) -> list[float]:
        """The cost of each camera, drawn together; ``_INVALID`` for None (coordinates that give
        no camera), which is not counted."""
        frames = iter(self.renderer.render_many(self.mesh, [c for c in cameras if c is not None]))
        return [_INVALID if cam is None else self._score(cam, next(frames)) for cam in cameras]

    def _score(self, cam: Camera, frame: Frame) -> float:
        value = self.edges(frame)
        if self.box is not None and self.box_points is not None and self.terms.box_weight > 0:
            value += self.terms.box_weight * box_overflow(cam, self.box_points, self.box, self.terms.box_tolerance,
                                                          self.terms.box_shortfall)
        self.count += 1
        if self.progress is not None and self.count % 20 == 0:
            self.progress(self.stage, self.count, value)
        return value


def _structure_size(work: npt.NDArray[np.uint8], options: RegistrationOptions) -> tuple[int, int]:
    """The size the structure is scored at: the working photo's, reduced to ``structure_size``
    pixels on its longer side (never enlarged)."""
    Hf, Wf = work.shape[:2]
    s = min(1.0, options.structure.structure_size / max(Wf, Hf))
    return max(8, round(Wf * s)), max(8, round(Hf * s))


class EdgeFit:
    """The chamfer of the model's edges against the photo's, as the free refinement of
    :func:`find_structure` scores it but without a box: at ``structure_size``, truncated at
    ``structure_tau``; called with cameras for the working photo ``work``. No box and no mask
    enter it, so poses found in different ways (the shading search's, the photo search's) are
    compared on one footing (``docs/decisions/0015-one-footing.md``). The photo's edges are
    found once, when it is made."""

    def __init__(self, work: npt.NDArray[np.uint8], model: VehicleModel, options: RegistrationOptions,
                 renderer: Renderer) -> None:
        self.size = _structure_size(work, options)
        self.cost = StructureCost(resized(work, *self.size), model.exterior(options.pyramid.min_faces, renderer),
                                  renderer, options, tau=options.structure.structure_tau)

    def __call__(self, cameras: list[Camera]) -> list[float]:
        return [self.cost(cam.scaled(*self.size)) for cam in cameras]


def find_structure(
    work: npt.NDArray[np.uint8],
    model: VehicleModel,
    start: Camera,
    box: Box,
    options: RegistrationOptions,
    renderer: Renderer,
    optimizer: Optimizer,
    progress: Progress | None = None,
) -> Structure:
    """The pose found on the photo's edges and the box (both stages of the module docstring).

    ``work`` is the working photo, ``start`` a camera for it, ``box`` the vehicle's box in its
    pixels. Runs at ``structure_size`` pixels (never enlarged).
    """
    t0 = time.perf_counter()
    st = options.structure
    Hf, Wf = work.shape[:2]
    w, h = _structure_size(work, options)
    image = resized(work, w, h)
    level_box: Box = (box[0] * w / Wf, box[1] * h / Hf, box[2] * w / Wf, box[3] * h / Hf)
    ref = start.scaled(w, h)
    points = model.mesh.extreme_points(_POINTS)
    centre = model.mesh.sphere[0]
    mesh = model.exterior(options.pyramid.min_faces, renderer)

    anchored = BoxAnchoredParams(ref, level_box, points, centre)
    objective = StructureCost(image, mesh, renderer, options, tau=st.anchor_tau, progress=progress,
                              stage=f"structure anchored ({w}x{h})")
    # The first generation's spread: the start's rotation error (5-15 degrees for a rough
    # start) about the image's horizontal and vertical axes, half that about the optical axis
    # (photos are mostly level), and a factor of two either way in focal length.
    spread = np.radians(st.structure_spread)
    steps = np.array([spread, spread, 0.5 * spread, 0.7])
    # Independent anchored searches, their means averaged: each search's mean still sits in one
    # of the floor's pits, a few degrees from its middle, and the pits differ from sample to
    # sample; their average is nearer the middle (docs/decisions/0016-averaged-anchors.md).
    elite = max(1, st.anchor_population // 10)
    found = [_search(CrossEntropy(population=st.anchor_population, elite=elite, seed=seed), objective, anchored,
                     anchored.start(), steps, st.anchor_evaluations)
             for seed in range(st.structure_seed, st.structure_seed + st.structure_runs)]
    x = np.mean([f.x for f in found], axis=0)
    camera = anchored.camera(x)
    anchored_camera = camera
    t1 = time.perf_counter()
    levels = [LevelReport(w, h, mesh.n_faces, sum(f.evaluations for f in found), sum(f.restarts for f in found),
                          float("nan"), t1 - t0, objective(camera))]

    free = ViewParams(camera, centre, options.probes.dolly_pivot * model.mesh.sphere[1])
    refine = StructureCost(image, mesh, renderer, options, tau=st.structure_tau, box=level_box, points=points,
                           progress=progress, stage=f"structure refined ({w}x{h})")
    res = _search(optimizer, refine, free, free.start(), 0.3 * free.steps(), st.structure_evaluations)
    if res.fun < refine(camera):
        camera = free.camera(res.x)
    levels.append(LevelReport(w, h, mesh.n_faces, res.evaluations, res.restarts, float("nan"),
                              time.perf_counter() - t1, res.fun))
    return Structure(levels, [anchored_camera.scaled(Wf, Hf), camera.scaled(Wf, Hf)], time.perf_counter() - t0)


def loss_at(work: npt.NDArray[np.uint8], foreground: npt.NDArray[np.bool_], camera: Camera, model: VehicleModel,
            options: RegistrationOptions, renderer: Renderer, width: int, height: int) -> float:
    """The named loss of ``camera`` (any size) on ``work`` and ``foreground`` reduced to ``width`` x ``height``."""
    return losses_at(work, foreground, camera, model, options, renderer, width, height)[0]


def losses_at(work: npt.NDArray[np.uint8], foreground: npt.NDArray[np.bool_], camera: Camera,
              model: VehicleModel, options: RegistrationOptions, renderer: Renderer, width: int,
              height: int) -> tuple[float, float | None]:
    """:func:`loss_at`, and with a colour loss on a colour photo the same loss on the photo's
    luminance, where the shading's thresholds are set
    (:meth:`~vehicle_pose.registration.fit.Fit.share`; else None), from one draw of the pose."""
    small, mask = resized(work, width, height), resized_mask(foreground, width, height)
    cam = camera.scaled(width, height)
    mesh = model.exterior(face_budget(float(max(silhouette(model, cam, renderer).sum(), 1)), options.pyramid),
                          renderer)
    frame = renderer.render(mesh, cam)
    loss = float(make_loss(options.loss, make_target(small, mask, color=options.color))(frame))
    if not options.color or is_gray(work):
        return loss, None
    return loss, float(make_loss(options.loss, make_target(small, mask, color=False))(frame))


def structure_fit(work: npt.NDArray[np.uint8], model: VehicleModel, structure: Structure, shaded: Fit,
                  options: RegistrationOptions, renderer: Renderer) -> Fit:
    """The structure's pose as a :class:`~vehicle_pose.registration.fit.Fit`, its levels' ``loss``
    the named loss of their pose on the shading fit's final mask at their own size (so that every
    registration reports the same measure), with that mask and the shading fit's GrabCut time."""
    reports = []
    for level, cam in zip(structure.levels, structure.cameras, strict=True):
        loss, luminance = losses_at(work, shaded.foreground, cam, model, options, renderer, level.width, level.height)
        reports.append(replace(level, loss=loss, luminance=luminance))
    return Fit(structure.camera, reports, shaded.foreground, 0.0)
