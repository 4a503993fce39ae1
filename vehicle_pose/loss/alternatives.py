"""The losses the search can minimise, filed in :data:`vehicle_pose.registry.LOSSES`: the
paper's invariant loss and alternatives to compare.

Every entry maps a :class:`PhotoTarget` to a callable scoring a rendered :class:`Frame` (lower is
better). The alternatives that need a shaded image use a fixed head-light:
``k_a * 0.3 + k_d * 0.7 * |n_z|`` on the model, 0 elsewhere.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from vehicle_pose.clock import timed
from vehicle_pose.loss.invariant import InvariantLoss, PartsInvariantLoss, PhotoTarget
from vehicle_pose.registry import LOSSES
from vehicle_pose.render.renderer import Frame, headlight

__all__ = ["make_loss", "headlight_shading"]

BoundLoss = Callable[[Frame], float]


def headlight_shading(frame: Frame) -> npt.NDArray[np.float32]:
    """Gray shading (N, 1) of the covered pixels under a light at the camera."""
    return headlight(frame.covered(frame.attrs))[:, None]


class _GrayTarget(InvariantLoss):
    """The invariant machinery on the photo's luminance (n = 1)."""

    @staticmethod
    def _photo_attributes(target: PhotoTarget) -> npt.NDArray[np.float64]:
        return target.gray()[..., None]


def correlation_loss(target: PhotoTarget) -> BoundLoss:
    """``1 - corr^2`` between the gray photo and a head-light shaded render (n = m = 1)."""
    return _GrayTarget(target, channels=headlight_shading)


def paper_channels(frame: Frame) -> npt.NDArray[np.float32]:
    """The paper's m = 4 channels (k_a, k_d * normal), without the coverage channel."""
    return frame.covered(frame.attrs)


def invariant_paper_loss(target: PhotoTarget) -> BoundLoss:
    """The paper's exact setting: gray photo (n = 1), m = 4 channels (k_a, k_d * normal)."""
    return _GrayTarget(target, channels=paper_channels)


class SquaredErrorLoss:
    """Mean squared difference between the gray photo and the head-light shaded render."""

    def __init__(self, target: PhotoTarget) -> None:
        g = target.gray()
        self._g = g.reshape(-1)
        self._w = target.weights.reshape(-1)
        self._sw = float(self._w.sum())
        self._base = float(self._w @ (self._g * self._g))

    @timed("loss")
    def __call__(self, frame: Frame) -> float:
        s = headlight_shading(frame)[:, 0].astype(np.float64)
        idx = frame.covered_flat_indices()
        w, g = self._w[idx], self._g[idx]
        return (self._base + float(w @ (s * s - 2.0 * g * s))) / self._sw


class SilhouetteIoULoss:
    """``1 - IoU`` between the model's coverage and the photo's foreground mask."""

    def __init__(self, target: PhotoTarget) -> None:
        self._fg = target.foreground.reshape(-1)
        self._n_fg = int(self._fg.sum())

    @timed("loss")
    def __call__(self, frame: Frame) -> float:
        idx = frame.covered_flat_indices()
        inter = int(self._fg[idx].sum())
        union = self._n_fg + idx.size - inter
        return 1.0 - inter / union if union else 1.0


class MutualInformationLoss:
    """``1 - 2 I(F; S) / (H(F) + H(S))`` over all weighted pixels, gray photo F, shading S."""

    def __init__(self, target: PhotoTarget, bins: int = 32) -> None:
        self.bins = bins
        g = target.gray().reshape(-1)
        self._w = target.weights.reshape(-1)
        self._fb = np.clip((g * bins).astype(np.intp), 0, bins - 1)
        # All pixels start in the model's "empty" bin 0; covered pixels move out of it.
        self._base = np.zeros((bins, bins + 1))
        np.add.at(self._base[:, 0], self._fb, self._w)

    @timed("loss")
    def __call__(self, frame: Frame) -> float:
        s = headlight_shading(frame)[:, 0]
        idx = frame.covered_flat_indices()
        sb = 1 + np.clip((s * self.bins).astype(np.intp), 0, self.bins - 1)
        joint = self._base.copy()
        w, fb = self._w[idx], self._fb[idx]
        np.add.at(joint[:, 0], fb, -w)
        np.add.at(joint, (fb, sb), w)
        p = joint / joint.sum()
        pf, ps = p.sum(1), p.sum(0)

        def entropy(q: npt.NDArray[np.float64]) -> float:
            q = q[q > 0]
            return float(-(q * np.log(q)).sum())

        hf, hs, hj = entropy(pf), entropy(ps), entropy(p.reshape(-1))
        if hf + hs <= 0:
            return 1.0
        return 1.0 - 2.0 * (hf + hs - hj) / (hf + hs)


for _name, _factory in (
    ("invariant", InvariantLoss),
    ("invariant-paper", invariant_paper_loss),
    ("invariant-parts", PartsInvariantLoss),
    ("correlation", correlation_loss),
    ("squared", SquaredErrorLoss),
    ("silhouette-iou", SilhouetteIoULoss),
    ("mutual-information", MutualInformationLoss),
):
    LOSSES.register(_name)(_factory)


def make_loss(name: str, target: PhotoTarget) -> BoundLoss:
    """The loss called ``name`` bound to ``target``; ValueError for an unknown name."""
    loss: BoundLoss = LOSSES.get(name)(target)
    return loss
