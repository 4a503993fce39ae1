"""The search without a start camera on a photo the shading does not explain
(``docs/decisions/0014-photo-search.md``).

On a real photo the no-hint search of :mod:`~vehicle_pose.registration.nohint` screens and
refines start poses on the invariant loss, and the loss does not explain the photo (sky and
buildings mirrored in the paint and the glass): its minimum is elsewhere, the pose is wrong by a
half turn or shrunk onto a panel. What holds on such a photo is coarser: the parts' colours
(:mod:`~vehicle_pose.loss.mutual`) and the structure's edges
(:mod:`~vehicle_pose.registration.structure`). So, as multi-hypothesis trackers do:

1. **Hypotheses**: a grid of views (every ``SearchGrid`` azimuth, ``photo_elevations``, no
   roll, a long lens of ``photo_focal`` image widths), each moved and scaled to fill each
   candidate box (the client's box; without one the whole frame, as a claims photo is mostly
   the car, and the region GrabCut found), scored by the material-colour mutual information
   on the whole frame. The best ``photo_hypotheses`` distinct views are kept: the colours tell
   the half turns apart, the edges of a view 90 or 180 degrees off can match as well.
2. **Refinement**: each found again on the photo's edges and its box
   (:func:`~vehicle_pose.registration.structure.find_structure`, as from a client's rough start).
3. **Verification**: the refined hypothesis with the lowest structure objective (the chamfer and
   the box term) wins; the colours, which ranked the hypotheses before the edges refined them,
   are the second, independent cue. The result is credible when both cues name the same pose
   (``cues_agree``) and the edges prefer it by a ``margin`` over the best hypothesis at least
   :data:`VERIFY_APART` degrees away.
4. **Against the shading pose** (:func:`photo_pose`): the winner was found in a box, the
   shading search's pose was not, so their structure objectives do not compare. Both are
   scored by the chamfer alone (no box, no mask), and the winner replaces the shading pose
   where it is lower: a shading pose shrunk onto a panel of a real photo scores 0.3-0.6 there,
   a right one on a render 0.07-0.11, the photo search's poses 0.13-0.46
   (``docs/decisions/0015-one-footing.md``). The winner also replaces a shading pose that
   the colours do not find a vehicle in, its material information below the median view of
   the grid's: on a photo of 100-200 pixels a pose shrunk onto the number plate can have the
   lower chamfer (``docs/decisions/0017-shading-pose-evidence.md``). A pose that replaces the
   shading pose also needs evidence of a vehicle: its chamfer's lead over the median view of
   the grid in its box (``edge_lead``; a photo of noise has edges everywhere, and every outline
   fits it alike).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from vehicle_pose.geometry.camera import Camera
from vehicle_pose.loss.mutual import MaterialInformation
from vehicle_pose.metrics import rotation_error
from vehicle_pose.model.library import VehicleModel
from vehicle_pose.registration.credibility import fit_checks
from vehicle_pose.registration.fit import Fit, Progress
from vehicle_pose.registration.options import RegistrationOptions
from vehicle_pose.registration.segmentation import resegment
from vehicle_pose.registration.structure import EdgeFit, Structure, find_structure, structure_fit
from vehicle_pose.render.renderer import Renderer
from vehicle_pose.search.optimize import Optimizer
from vehicle_pose.search.views import DISTINCT_ANGLE, Box, Candidate, SearchGrid, distinct, fit_to_box, view_camera
from vehicle_pose.segment.region import VehicleRegion

__all__ = ["Hypothesis", "PhotoPose", "PhotoSearch", "photo_pose", "photo_search", "with_neighbours", "VERIFY_APART"]

VERIFY_APART = 15.0
"""Degrees apart at which two refined hypotheses are two poses rather than one found twice (the
no-hint search's rivals are as far apart, ``docs/decisions/0008-confidence.md``)."""


@dataclass
class Hypothesis:
    """One refined hypothesis: the view it started from (its colour information in the
    detail), its box and its structure search."""

    start: Candidate
    box: Box
    structure: Structure

    @property
    def information(self) -> float:
        return self.start.detail["information"]

    @property
    def camera(self) -> Camera:
        return self.structure.camera

    @property
    def objective(self) -> float:
        return self.structure.levels[-1].objective


@dataclass
class PhotoSearch:
    """The hypotheses, best first, the time spent, every view of the grid as scored, and the
    colour information they were scored with."""

    hypotheses: list[Hypothesis]
    seconds: float
    views: list[Candidate]
    information: MaterialInformation

    @property
    def best(self) -> Hypothesis:
        return self.hypotheses[0]

    @property
    def checks(self) -> dict[str, float]:
        """``margin``: the winner's relative lead on the structure objective over the best
        hypothesis at least :data:`VERIFY_APART` degrees away (1 when there is none);
        ``cues_agree``: 1 when the winner is (within :data:`VERIFY_APART` degrees) the hypothesis
        the colours ranked first, else 0; ``photo_search``: 1 (the confidence reads these)."""
        best = self.best
        rivals = [h.objective for h in self.hypotheses[1:]
                  if rotation_error(h.camera.R, best.camera.R) >= VERIFY_APART]
        margin = (min(rivals) - best.objective) / max(abs(min(rivals)), 1e-9) if rivals else 1.0
        first = max(self.hypotheses, key=lambda h: h.information)
        agree = first is best or rotation_error(first.camera.R, best.camera.R) < VERIFY_APART
        return {"margin": margin, "cues_agree": float(agree), "photo_search": 1.0}

    def listed(self) -> list[dict[str, Any]]:
        """The hypotheses as the result reports them."""
        return [h.start.to_dict() | {"box": list(h.box), "structure_objective": h.objective}
                for h in self.hypotheses]


def photo_search(
    work: npt.NDArray[np.uint8],
    model: VehicleModel,
    boxes: list[Box],
    options: RegistrationOptions,
    renderer: Renderer,
    optimizer: Optimizer,
    progress: Progress | None = None,
) -> PhotoSearch:
    """Hypotheses on the grid fitted to each of ``boxes``, refined on the edges, verified (the
    module docstring); ``work`` is the working photo, the boxes in its pixels."""
    t0 = time.perf_counter()
    Hf, Wf = work.shape[:2]
    search = options.search
    mesh = model.exterior(options.pyramid.min_faces, renderer)
    score = MaterialInformation(work, mesh, renderer, size=options.structure.structure_size,
                                clusters=search.photo_clusters)
    points, centre = model.mesh.extreme_points(600), model.mesh.sphere[0]
    cands = []
    for k, box in enumerate(boxes):
        for az in SearchGrid().azimuths:
            for el in search.photo_elevations:
                cam = view_camera(model, az, el, 0.0, box, Wf, Hf, search.photo_focal * Wf)
                cam = fit_to_box(cam, points, centre, box, rounds=4, clip=True)
                information = score(cam)
                cands.append(Candidate(cam, "photo-search", score=-information,
                                       detail={"azimuth": az, "elevation": el, "box_index": float(k),
                                               "information": information}))
    # From a grid view far from the truth, independent anchored searches can end in different
    # basins (a view and its mirror twin) and their average in neither: each hypothesis gets one
    # search of the same budget (docs/decisions/0016-averaged-anchors.md).
    st = options.structure
    single = options.replace(structure_runs=1, anchor_evaluations=st.structure_runs * (st.anchor_evaluations - 1) + 1)
    hypotheses = []
    chosen = with_neighbours(distinct(cands, search.photo_hypotheses), cands, search.photo_neighbours)
    for k, cand in enumerate(chosen):
        if progress is not None:
            progress(f"photo search: hypothesis {k + 1}/{len(chosen)}", 0, float("nan"))
        box = boxes[int(cand.detail["box_index"])]
        found = find_structure(work, model, cand.camera, box, single, renderer, optimizer, progress)
        hypotheses.append(Hypothesis(cand, box, found))
    hypotheses.sort(key=lambda h: h.objective)
    return PhotoSearch(hypotheses, time.perf_counter() - t0, cands, score)


def with_neighbours(chosen: list[Candidate], views: list[Candidate], count: int) -> list[Candidate]:
    """``chosen`` (the distinct views, best first) and, for each of the first ``count``, the best
    view of ``views`` in the same box that the distinct choice set aside next to it (within
    :data:`~vehicle_pose.search.views.DISTINCT_ANGLE`).

    The colours rank a view and its neighbour alike, and the distinct choice keeps only one of
    them; where the one kept is a grid step too far for the refinement to cross, its neighbour
    is the start that reaches the pose (real 05116: the colours' first view, 25 degrees off,
    ends there; its best neighbour set aside, 10.6 degrees off, ends 7.9 degrees off;
    docs/decisions/0019-colour-neighbour.md)."""
    out = list(chosen)
    for cand in chosen[:count]:
        near = [v for v in views if all(v is not k for k in out)
                and v.detail["box_index"] == cand.detail["box_index"]
                and rotation_error(v.camera.R, cand.camera.R) < DISTINCT_ANGLE]
        if near:
            out.append(min(near, key=lambda v: v.score))
    return out


@dataclass
class PhotoPose:
    """What the photo search does to a no-hint registration: ``fit``, its pose as a fit (None
    where the shading pose is kept), ``start``, the winning hypothesis's start view,
    ``checks``, the checks of the pose kept (both edge costs added), ``listed``, the hypotheses
    tried, and the time spent searching and segmenting again."""

    fit: Fit | None
    start: Candidate
    checks: dict[str, float]
    listed: list[dict[str, Any]]
    seconds: float
    grabcut_seconds: float


def photo_pose(work: npt.NDArray[np.uint8], model: VehicleModel, rect: Box | None, region: VehicleRegion,
               shaded: Fit, checks: dict[str, float], options: RegistrationOptions, renderer: Renderer,
               optimizer: Optimizer, progress: Progress | None = None) -> PhotoPose:
    """The photo search in the client's box ``rect`` (otherwise the whole frame and the box of
    the ``region`` found), and the verification against the shading search's pose ``shaded``
    (its checks ``checks``): the winner replaces it when the model's edges fit the photo's
    better there (:class:`~vehicle_pose.registration.structure.EdgeFit`, no box and no mask),
    or when the shading pose's colour information is below the median view of the grid's (step
    4 of the module docstring; both edge costs, the shading pose's information and the grid's
    median are reported). The pose that replaces it is reported with the shading fit's mask
    segmented again around it, and its checks (``shading_loss`` the loss it replaced)."""
    Hf, Wf = work.shape[:2]
    boxes = [rect] if rect is not None else [(0.0, 0.0, Wf - 1.0, Hf - 1.0), region.box]
    found = photo_search(work, model, boxes, options, renderer, optimizer, progress)
    best = found.best
    edge_fit = EdgeFit(work, model, options, renderer)
    shading_edges, photo_edges = edge_fit([shaded.camera, best.camera])
    # The shading pose is kept only where the colours also find a vehicle there: its parts split
    # the photo's colours at least as well as the median view of the grid does. A pose shrunk
    # onto a panel can have the lower chamfer (its few edges on the panel's) and splits off
    # next to nothing (docs/decisions/0017-shading-pose-evidence.md).
    shading_information = found.information(shaded.camera)
    grid_information = float(np.median([v.detail["information"] for v in found.views]))
    evidence = {"shading_edges": shading_edges, "photo_edges": photo_edges,
                "shading_information": shading_information, "grid_information": grid_information}
    if photo_edges >= shading_edges and shading_information >= grid_information:
        return PhotoPose(None, best.start, checks | evidence, found.listed(), found.seconds, 0.0)
    # The evidence that there is a vehicle at all: how much closer the winner's edges lie than
    # those of a typical view of the grid in the same box (a photo of noise, edges everywhere,
    # fits every outline alike).
    box_index = best.start.detail["box_index"]
    grid = [v.camera for v in found.views if v.detail["box_index"] == box_index]
    evidence["edge_lead"] = 1.0 - photo_edges / max(float(np.median(edge_fit(grid))), 1e-9)
    t = time.perf_counter()
    again = resegment(work, model, best.camera, options.segmentation, renderer, None, max(Wf, Hf))
    grabcut = time.perf_counter() - t
    masked = replace(shaded, foreground=shaded.foreground if again is None else again)
    fitted = structure_fit(work, model, best.structure, masked, options, renderer)
    kept = (found.checks | fit_checks(work, model, fitted, region, options.color, renderer)
            | {"shading_loss": checks["loss"]} | evidence)
    return PhotoPose(fitted, best.start, kept, found.listed(), found.seconds, grabcut)
