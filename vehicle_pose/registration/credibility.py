"""Is a registered pose credible? The checks behind ``confidence`` and ``failed``
(``docs/decisions/0008-confidence.md``)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from vehicle_pose.metrics import iou
from vehicle_pose.model.library import VehicleModel
from vehicle_pose.registration.fit import Fit
from vehicle_pose.registration.segmentation import silhouette
from vehicle_pose.render.renderer import Renderer
from vehicle_pose.segment.region import VehicleRegion

__all__ = ["confidence", "fit_checks"]


BOX_AGREEMENT = 0.5
"""The IoU of a pose's projected box with the client's box at which the pose's agreement with
the box scores 0.5 (1 from 0.2 more, 0 at 0.2 less): the criterion by which a detection matches
an object (IoU 0.5, PASCAL VOC), here asked of the registered model against the client's box
(``docs/decisions/0041-camera-and-box-by-the-view-sphere.md``)."""


def confidence(checks: dict[str, float]) -> float:
    """How credible a pose is, in [0, 1]; below 0.5 is ``failed``: :func:`_pose_confidence`,
    and with a client's box at most the pose's agreement with it (``box_agreement``, the IoU of
    the projection's box cut to the frame with the client's box; 0.5 at :data:`BOX_AGREEMENT`):
    a pose whose outline does not match the box the client drew is not a registration of the
    vehicle in it, whatever the edges or the shading say of the pose in its own box."""
    score = _pose_confidence(checks)
    if "box_agreement" in checks:
        score = min(score, float(np.clip(0.5 + 2.5 * (checks["box_agreement"] - BOX_AGREEMENT), 0.0, 1.0)))
    return score


def _pose_confidence(checks: dict[str, float]) -> float:
    """How credible a pose is, in [0, 1], from its own checks.

    A pose of the view-sphere search, or any pose from a start camera (``two_way`` in the
    checks): :func:`_edge_confidence`. A pose of the classic chain (``pose_search="classic"``)
    without a start camera: the weakest of three scores, each 0.5 at its threshold:

    - fit: the final loss over its maximum, 1 up to 0.10, 0.5 at 0.15, 0 from 0.20;
    - uniqueness: the relative loss margin over the best alternative at least 15 degrees away,
      0.5 at 0.15, 1 from 0.35 (``agreement``, the share of other starts that converged to
      the same pose, is reported but does not count: a wrong front/back twin can gather
      starts as well);
    - region: the final silhouette's IoU with the vehicle's region found before any pose was
      known, 0.5 at 0.7, 1 from 0.9.

    A pose of the photo search (``photo_search`` in the checks,
    ``docs/decisions/0014-photo-search.md``) has no credible loss to judge: there the two cues
    decide. When the colours and the edges name the same pose (``cues_agree``) the confidence is
    0.5 + 0.5 x the uniqueness, else 0.45 x it (always failed); and it is at most the evidence
    of a vehicle, the chamfer's lead over the median view of the grid (``edge_lead``), 0.5 at
    0.2 and 1 from 0.35 (``docs/decisions/0015-one-footing.md``).
    """
    if "two_way" in checks:
        return _edge_confidence(checks)
    unique = _loss_uniqueness(checks.get("margin", 0.0))
    if checks.get("photo_search"):
        u = float(np.clip(unique, 0.0, 1.0))
        cues = 0.5 + 0.5 * u if checks.get("cues_agree") else 0.45 * u
        evidence = (checks.get("edge_lead", 0.0) - 0.05) / 0.30
        return float(np.clip(min(cues, evidence), 0.0, 1.0))
    fit = (0.20 - checks.get("loss", 1.0)) / 0.10
    region = (checks.get("region_iou", 0.0) - 0.5) / 0.40
    return float(np.clip(min(fit, unique, region), 0.0, 1.0))


def _loss_uniqueness(margin: float) -> float:
    """Uniqueness from the relative margin of a pose's loss over the best other pose's, 0.5 at
    0.15 and 1 from 0.35 (unclipped; ``docs/decisions/0008-confidence.md``)."""
    return (margin + 0.05) / 0.40


MARGIN = 0.065
"""The view-sphere search's relative margin over the best pose at least 15 degrees away at which
its uniqueness is 0.5 (``docs/decisions/0020-view-sphere-search.md``: chosen on half a of the
real photos, checked on half b and on the partial views)."""


def _edge_confidence(checks: dict[str, float]) -> float:
    """The confidence of a pose of the view-sphere search, or of any pose from a start camera:
    the evidence of a vehicle along the pose's outline, and without a start camera also the
    pose's uniqueness; each score 0.5 at its threshold.

    - evidence: the pose's two-way chamfer explains most of the edges in the box of its
      projection (``two_way``; 0.5 at 0.70, 1 up to 0.55), and leads the median of a ring of
      other views placed in that box (``edge_lead``; 0.5 at 0.20, 1 from 0.35) or the shading
      explains the photo (the loss over its maximum, 0.5 at 0.15: a render, a matte car, whose
      outline may lead little): noise leads nothing, an empty photo explains nothing, and a
      smooth background's shading fitted on GrabCut's mask of it explains no edge
      (``docs/decisions/0042-the-shading-is-not-the-edges.md``);
    - uniqueness (no start camera): the relative margin over the best pose at least 15 degrees
      away (``margin``; 0.5 at :data:`MARGIN`, 1 from 0.2 more); where the shading confirmed the
      pose and judged its rival (``shading_margin``), the relative margin of the two poses'
      losses instead, scored as the classic chain scores it (0.5 at 0.15, 1 from 0.35): there
      the shading, not the edges, chose the pose
      (``docs/decisions/0033-the-shading-judges-its-rival.md``). Where the edges chose and the
      search sizes voted without all agreeing (``sizes_agree`` under 1), at most half that
      share: the edges do not decide the pose (``docs/decisions/0036-sizes-vote.md``).
    """
    lead = float(np.clip((checks.get("edge_lead", 0.0) - 0.05) / 0.30, 0.0, 1.0))
    explained = float(np.clip((0.85 - checks["two_way"]) / 0.30, 0.0, 1.0))
    fit = float(np.clip((0.20 - checks.get("loss", 1.0)) / 0.10, 0.0, 1.0))
    # The shading's explanation stands in for the lead over other views (a matte car's outline
    # may lead little), not for the edges themselves: a pose that explains none of the edges in
    # its box is no vehicle, however well a smooth background's shading fits it.
    vehicle = min(explained, max(fit, lead))
    if checks.get("hinted"):
        return vehicle
    if "shading_margin" in checks:
        unique = float(np.clip(_loss_uniqueness(checks["shading_margin"]), 0.0, 1.0))
    else:
        unique = float(np.clip(0.5 + 2.5 * (checks.get("margin", 0.0) - MARGIN), 0.0, 1.0))
        agree = checks.get("sizes_agree", 1.0)
        if agree < 1.0:
            unique = min(unique, 0.5 * agree)
    return min(unique, vehicle)


def fit_checks(
    work: npt.NDArray[np.uint8],
    model: VehicleModel,
    fitted: Fit,
    region: VehicleRegion | None,
    color: bool,
    renderer: Renderer,
) -> dict[str, float]:
    """The final pose's silhouette against the region found before any pose was known
    (``region_iou``) and against its own foreground (``foreground_iou``), and its loss over the
    loss's maximum (``loss``), on the photo's luminance (:meth:`Fit.share`)."""
    final = silhouette(model, fitted.camera, renderer)
    checks = {} if region is None else {"region_iou": iou(final, region.mask)}
    checks["foreground_iou"] = iou(final, fitted.foreground)
    checks["loss"] = fitted.share(work, color)
    return checks
