"""What a registration returns: the pose, how it was found, and how credible it is."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from vehicle_pose.geometry.camera import Camera
from vehicle_pose.geometry.pose import Theta
from vehicle_pose.model.library import VehicleModel
from vehicle_pose.registration.options import RegistrationOptions
from vehicle_pose.render.parts import PartMap

__all__ = ["LevelReport", "RegistrationResult"]


@dataclass(frozen=True)
class LevelReport:
    """What one pyramid level did. ``loss`` is the named loss at the level's pose,
    ``objective`` what the search minimised: the loss plus the edge and box terms;
    ``luminance``, where the loss is a colour loss, the same loss on the photo's luminance at
    that pose (None where the loss is the luminance's already)."""

    width: int
    height: int
    faces: int
    evaluations: int
    restarts: int
    loss: float
    seconds: float
    objective: float
    luminance: float | None = None


@dataclass
class RegistrationResult:
    """A registered pose and how it was found.

    ``camera`` maps mesh coordinates to pixels of the photo as given (OpenCV convention);
    ``foreground`` is the GrabCut mask at the photo's size. ``start_source`` is the hint the
    client gave (``init_camera``, ``bbox`` or ``none``), ``start_method`` how the winning start
    was found (``given``, ``view-search`` or ``wheels``). ``confidence`` (in [0, 1], see
    :func:`~vehicle_pose.registration.credibility.confidence`) and ``failed`` judge a pose found
    without a start camera; ``checks``
    holds the measures behind them (and, for every run, ``foreground_iou``, the final
    silhouette against the final GrabCut mask, and ``loss``, the final loss over its maximum;
    ``passes`` is 2 when a second search ran);
    ``candidates`` lists the screened starts (for the view-sphere search, its refined poses,
    each with its ``source``: ``view-sphere``, ``half-turn twin`` or ``start``). ``evaluations``
    and ``restarts`` count every search run, screening included; ``levels`` are the winning
    pose's levels. ``pose_stage`` says which stage's pose is the result: ``shading`` (the
    loss's fit) or ``structure`` (edges and box, kept where the loss does not explain the
    photo; ``docs/decisions/0012-structure-first.md``). ``parts`` is the part map at the final pose
    (:mod:`vehicle_pose.render.parts`): which part each pixel of the photo shows; the JSON
    lists the visible parts. ``focal`` says where the focal length came from (``source``:
    ``exif`` where the photo's EXIF held the search, else ``searched``), the one found
    (``pixels``, ``widths``) and the EXIF's reading (``exif``, None without one);
    ``warnings`` are what the client should know of its input (EXIF that cannot be right).
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
    pose_stage: str = "shading"
    parts: PartMap | None = field(default=None, repr=False)
    focal: dict[str, Any] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)

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
            "pose_stage": self.pose_stage,
            "focal": self.focal,
            "warnings": self.warnings,
            "parts": self.parts.to_list() if self.parts is not None else [],
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
            "options": self.options.flat(),
            "cam_R_m2c": cam.R.reshape(-1).tolist(),
            "cam_t_m2c": cam.t.tolist(),
            "cam_K": cam.K.reshape(-1).tolist(),
        }
