"""Pose error metrics, one definition each, for the tests, the benchmarks and the engine.

Named as in the BOP toolkit's ``pose_error``: arguments are the estimate first, then the truth.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:
    from vehicle_pose.geometry.camera import Camera

__all__ = ["rotation_error", "projection_error", "iou"]


def rotation_error(R_est: npt.ArrayLike, R_gt: npt.ArrayLike) -> float:
    """Angle (degrees) of the rotation between two rotation matrices (3, 3), from the trace of
    ``R_est R_gt^T`` (good to about 1e-5 degrees near zero)."""
    a, b = np.asarray(R_est, np.float64), np.asarray(R_gt, np.float64)
    c = (np.trace(a @ b.T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def projection_error(points: npt.NDArray[np.float64], est: Camera, gt: Camera, *, width: float | None = None) -> float:
    """Mean distance (pixels) between ``points`` (N, 3, mesh units) projected by two cameras.

    With ``width``, distances are scaled to an image ``width`` pixels wide (the benchmarks
    report errors at 640 pixels). Infinite when a point is behind either camera.
    """
    d = np.linalg.norm(est.project(points) - gt.project(points), axis=1)
    if not np.all(np.isfinite(d)):
        return float("inf")
    return float(d.mean() * (1.0 if width is None else width / gt.width))


def iou(a: npt.NDArray[np.bool_], b: npt.NDArray[np.bool_]) -> float:
    """Intersection over union of two masks of one shape; 0 when both are empty."""
    union = float((a | b).sum())
    return float((a & b).sum()) / union if union else 0.0
