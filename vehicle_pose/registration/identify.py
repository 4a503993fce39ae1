"""Model identification (the seed paper's outlook): which of several models is in the photo?

Each candidate model is registered onto the photo (with the client's hint, or none) and the
models are ranked by how well their registered pose explains the photo: the final invariant
loss over its maximum plus the silhouette's disagreement with the vehicle's GrabCut mask
(1 - IoU). The loss alone favours a model whose silhouette shrinks inside the vehicle; the
silhouette term penalises that.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from vehicle_pose.errors import PoseError
from vehicle_pose.geometry.camera import Camera
from vehicle_pose.model.library import VehicleModel
from vehicle_pose.photo import ExifFocal
from vehicle_pose.registration.options import RegistrationOptions
from vehicle_pose.registration.register import register
from vehicle_pose.registration.result import RegistrationResult
from vehicle_pose.render.renderer import Renderer

__all__ = ["Identification", "identify", "fit_score", "register_or_identify"]


def fit_score(result: RegistrationResult) -> float:
    """Lower is better: normalised loss + (1 - silhouette IoU with the GrabCut mask)."""
    return float(result.checks["loss"] + (1.0 - result.checks["foreground_iou"]))


@dataclass(frozen=True)
class Identification:
    """One candidate model's registration and its score (lower is better)."""

    model: VehicleModel
    result: RegistrationResult | None
    score: float
    error: str | None = None

    @property
    def camera(self) -> Camera:
        assert self.result is not None
        return self.result.camera

    def to_dict(self) -> dict[str, object]:
        return {
            "model": self.model.info.id,
            "score": self.score if np.isfinite(self.score) else None,
            "loss": None if self.result is None else self.result.loss,
            "confidence": None if self.result is None else self.result.confidence,
            "error": self.error,
        }


def identify(
    photo: npt.NDArray[np.uint8],
    models: Sequence[VehicleModel],
    *,
    init_camera: Camera | None = None,
    bbox: str | Sequence[float] | None = None,
    options: RegistrationOptions = RegistrationOptions(),
    renderer: Renderer | None = None,
    progress: Callable[[str, int, float], None] | None = None,
    photo_size: tuple[int, int] | None = None,
    exif: ExifFocal | None = None,
    deadline: float | None = None,
) -> list[Identification]:
    """Register every model and rank them, best first.

    A model whose registration cannot start (its start pose puts it off-screen) ranks last
    with its reason; the others are unaffected. Raises ValueError for an empty list.
    """
    if not models:
        raise ValueError("identification needs at least one candidate model")
    renderer = renderer if renderer is not None else Renderer()
    out = []
    for k, model in enumerate(models):
        stage = f"model {k + 1}/{len(models)} {model.info.id}: "

        def relay(name: str, evaluations: int, loss: float, stage: str = stage) -> None:
            if progress is not None:
                progress(stage + name, evaluations, loss)

        try:
            res = register(photo, model, init_camera=init_camera, bbox=bbox, options=options,
                           renderer=renderer, progress=relay, photo_size=photo_size, exif=exif, deadline=deadline)
        except PoseError as exc:
            out.append(Identification(model, None, float("inf"), str(exc)))
            continue
        out.append(Identification(model, res, fit_score(res)))
    return sorted(out, key=lambda c: c.score)


def register_or_identify(
    photo: npt.NDArray[np.uint8],
    models: Sequence[VehicleModel],
    *,
    init_camera: Camera | None = None,
    bbox: str | Sequence[float] | None = None,
    options: RegistrationOptions = RegistrationOptions(),
    renderer: Renderer | None = None,
    progress: Callable[[str, int, float], None] | None = None,
    photo_size: tuple[int, int] | None = None,
    exif: ExifFocal | None = None,
    deadline: float | None = None,
) -> tuple[RegistrationResult, dict[str, Any]]:
    """Register the one model given, or identify the model among several: the winning
    registration and its JSON result (with the ranking under ``identification`` when several
    models were tried). PoseError when no candidate could be registered. ``photo_size`` as
    ``exif`` and ``deadline`` as for :func:`~vehicle_pose.registration.register.register`."""
    if len(models) == 1:
        result = register(photo, models[0], init_camera=init_camera, bbox=bbox, options=options,
                          renderer=renderer, progress=progress, photo_size=photo_size, exif=exif,
                          deadline=deadline)
        return result, result.to_dict()
    ranking = identify(photo, models, init_camera=init_camera, bbox=bbox, options=options,
                       renderer=renderer, progress=progress, photo_size=photo_size, exif=exif, deadline=deadline)
    best = ranking[0].result
    if best is None:
        raise PoseError(f"no candidate model could be registered: {ranking[0].error}")
    return best, best.to_dict() | {"identification": [c.to_dict() for c in ranking]}
