"""The illumination-invariant loss (method.md §2).

``Loss = min(n, m) - tr[C_FM C_MM^-1 C_MF C_FF^-1]`` where F holds the photo's ``n`` attributes
per pixel and M the rendered model's ``m`` attributes. The trace is the sum of the squared
canonical correlations between F and M, so the loss lies in ``[0, min(n, m)]``, is zero iff an
affine map sends M exactly onto F, and is unchanged by any regular linear map of F or of M.

Singular covariances (a flat-shaded model, a constant photo, a model covering every pixel) are
handled with a spectral pseudo-inverse: directions with no variance carry no information and are
dropped. A model covering (almost) no pixel scores the maximum ``min(n, m)``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from vehicle_pose.clock import timed
from vehicle_pose.loss.moments import frame_loss
from vehicle_pose.photo import is_gray
from vehicle_pose.render.renderer import Frame

__all__ = [
    "PhotoTarget",
    "make_target",
    "InvariantLoss",
    "PartsInvariantLoss",
    "invariant_loss",
    "loss_from_moments",
    "normal_channels",
    "part_channels",
]

FloatArray = npt.NDArray[np.float64]

# Relative eigenvalue below which a covariance direction counts as empty.
_RTOL = 1e-12


@dataclass(frozen=True)
class PhotoTarget:
    """A photo prepared for scoring at one resolution.

    Parameters
    ----------
    image : (H, W, n) float64
        Photo attributes, background pixels already zeroed.
    weights : (H, W) float64
        Per-pixel weight (1 for a plain image).
    foreground : (H, W) bool
        Pixels believed to show the vehicle (all True when unknown).
    """

    image: FloatArray
    weights: FloatArray
    foreground: npt.NDArray[np.bool_]
    _cache: dict[str, FloatArray] = field(default_factory=dict, repr=False, compare=False)

    @property
    def height(self) -> int:
        return int(self.image.shape[0])

    @property
    def width(self) -> int:
        return int(self.image.shape[1])

    @property
    def channels(self) -> int:
        return int(self.image.shape[2])

    def gray(self) -> FloatArray:
        """(H, W) luminance of the image (the image itself when n = 1)."""
        if "gray" not in self._cache:
            img = self.image
            g = img[..., 0] if img.shape[2] == 1 else img @ np.array([0.299, 0.587, 0.114])[: img.shape[2]]
            self._cache["gray"] = np.ascontiguousarray(g)
        return self._cache["gray"]


def make_target(rgb: npt.NDArray[np.uint8], foreground: npt.NDArray[np.bool_], *, color: bool,
                weights: FloatArray | None = None) -> PhotoTarget:
    """Photo attributes in [0, 1] with the background zeroed (n = 3 for colour, else 1)."""
    img = rgb.astype(np.float64) / 255.0
    if not color or is_gray(rgb):
        img = img @ np.array([0.299, 0.587, 0.114])
        img = img[..., None]
    img[~foreground] = 0.0
    return PhotoTarget(img, np.ones(foreground.shape) if weights is None else weights, foreground)


def _inv_sqrt(cov: FloatArray) -> FloatArray:
    """Columns spanning cov's range, scaled so that ``W.T @ cov @ W = I``; shape (k, r)."""
    evals, evecs = np.linalg.eigh(cov)
    top = float(evals[-1]) if evals.size else 0.0
    if not np.isfinite(top) or top <= 0.0:
        return np.zeros((cov.shape[0], 0))
    keep = evals > _RTOL * top
    whitening: npt.NDArray[np.float64] = evecs[:, keep] / np.sqrt(evals[keep])
    return whitening


def _photo_whitening(sw: float, s_f: FloatArray, s_ff: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The photo's mean (n,) and whitening ``W_F`` (n, r), ``W_F^T C_FF W_F = I`` over C_FF's
    range, from its weighted sums; r = 0 when there is nothing to whiten."""
    n = len(s_f)
    if sw <= 0.0:
        return np.zeros(n), np.zeros((n, 0))
    mean_f = s_f / sw
    c_ff = s_ff / sw - np.outer(mean_f, mean_f)
    if not np.all(np.isfinite(c_ff)):
        return mean_f, np.zeros((n, 0))
    return mean_f, _inv_sqrt(c_ff)


def _whitened_loss(sw: float, mean_f: FloatArray, w_f: FloatArray, s_m: FloatArray, s_fm: FloatArray,
                   s_mm: FloatArray) -> float:
    """:func:`loss_from_moments` with the photo's side already whitened (:func:`_photo_whitening`)."""
    n, m = s_fm.shape
    worst = float(min(n, m))
    if sw <= 0.0 or w_f.shape[1] == 0:
        return worst
    mean_m = s_m / sw
    c_mm = s_mm / sw - np.outer(mean_m, mean_m)
    c_fm = s_fm / sw - np.outer(mean_f, mean_m)
    if not (np.all(np.isfinite(c_mm)) and np.all(np.isfinite(c_fm))):
        return worst
    w_m = _inv_sqrt(c_mm)
    if w_m.shape[1] == 0:
        return worst
    t = w_f.T @ c_fm @ w_m
    explained = float(np.sum(t * t))
    return float(min(max(worst - explained, 0.0), worst))


def loss_from_moments(
    sw: float,
    s_f: FloatArray,
    s_m: FloatArray,
    s_ff: FloatArray,
    s_fm: FloatArray,
    s_mm: FloatArray,
) -> float:
    """The invariant loss from weighted raw moments.

    Parameters
    ----------
    sw : float
        Sum of weights over the pixel set.
    s_f, s_m : (n,), (m,)
        Weighted sums of F and M.
    s_ff, s_fm, s_mm : (n, n), (n, m), (m, m)
        Weighted sums of the outer products F F^T, F M^T, M M^T.
    """
    mean_f, w_f = _photo_whitening(sw, s_f, s_ff)
    return _whitened_loss(sw, mean_f, w_f, s_m, s_fm, s_mm)


def invariant_loss(
    f: npt.ArrayLike, m: npt.ArrayLike, weights: npt.ArrayLike | None = None
) -> float:
    """The invariant loss between two sets of per-pixel attributes.

    Parameters
    ----------
    f : (N, n) or (N,)
        Photo attributes.
    m : (N, m) or (N,)
        Model attributes.
    weights : (N,), optional
        Non-negative pixel weights.
    """
    fa = np.asarray(f, dtype=np.float64)
    ma = np.asarray(m, dtype=np.float64)
    fa = fa[:, None] if fa.ndim == 1 else fa
    ma = ma[:, None] if ma.ndim == 1 else ma
    if fa.shape[0] != ma.shape[0]:
        raise ValueError(f"f has {fa.shape[0]} pixels but m has {ma.shape[0]}")
    w = np.ones(fa.shape[0]) if weights is None else np.asarray(weights, dtype=np.float64)
    fw = fa * w[:, None]
    mw = ma * w[:, None]
    return loss_from_moments(
        float(w.sum()), fw.sum(0), mw.sum(0), fw.T @ fa, fw.T @ ma, mw.T @ ma
    )


def normal_channels(frame: Frame) -> npt.NDArray[np.float32]:
    """(1, k_a, k_d * normal) on the covered pixels; shape (N, 5).

    The leading coverage channel is the paper's k_a of an untextured model. It is kept beside
    the material albedo k_a because the photo's background is zeroed: a photo whose vehicle
    region carries an offset (any negative, any lighting with I_0 != 0) is then still an exact
    affine function of M.
    """
    a = frame.covered(frame.attrs)
    return np.concatenate([np.ones((a.shape[0], 1), np.float32), a], axis=1)


def part_channels(frame: Frame) -> npt.NDArray[np.float32]:
    """(k_a, k_d * normal) plus one indicator per material kind on the covered pixels."""
    base = frame.covered(frame.attrs)
    labels = frame.covered(frame.labels)
    onehot = (labels[:, None] == np.arange(1, frame.n_parts + 1)[None, :]).astype(np.float32)
    return np.concatenate([onehot, base], axis=1)


ChannelFn = Callable[[Frame], npt.NDArray[np.floating]]


class InvariantLoss:
    """The invariant loss bound to one photo; evaluating it costs O(silhouette pixels).

    Parameters
    ----------
    target : PhotoTarget
        The photo; its moments are accumulated once here, in float64.
    channels : callable, keyword-only
        Maps a rendered frame to the model attributes of its covered pixels, shape (N, m).
    min_pixels : int, keyword-only
        A model covering fewer pixels scores the maximum.
    """

    name = "invariant"

    def __init__(
        self, target: PhotoTarget, *, channels: ChannelFn = normal_channels, min_pixels: int = 16
    ) -> None:
        self.target = target
        self.channels = channels
        self.min_pixels = min_pixels
        h, w, n = target.image.shape
        weights = target.weights.reshape(-1).astype(np.float64)
        photo = self._photo_attributes(target).reshape(h * w, -1)
        self._w = weights
        self._fw = photo * weights[:, None]
        self._sw = float(weights.sum())
        self._s_f = self._fw.sum(0)
        self._s_ff = self._fw.T @ photo
        self.n = photo.shape[1]
        self._unit_weights = bool(np.all(weights == 1.0))
        # The photo's side of the loss, once.
        self._mean_f, w_f = _photo_whitening(self._sw, self._s_f, self._s_ff)
        self._w_f = np.ascontiguousarray(w_f)

    @staticmethod
    def _photo_attributes(target: PhotoTarget) -> FloatArray:
        return target.image

    def max_value(self, m: int) -> float:
        return float(min(self.n, m))

    @timed("loss")
    def __call__(self, frame: Frame) -> float:
        if self.channels is normal_channels:
            return self._compiled(frame, merge=True)
        attrs = self.channels(frame)
        m = attrs.shape[1]
        if attrs.shape[0] < self.min_pixels:
            return self.max_value(m)
        idx = frame.covered_flat_indices()
        n = self.n
        left = np.empty((idx.size, 1 + n))
        left[:, 0] = np.take(self._w, idx)
        left[:, 1:] = np.take(self._fw, idx, axis=0)
        mf = attrs.astype(np.float64)
        cross = left.T @ mf
        s_m, s_fm = cross[0], cross[1:]
        s_mm = mf.T @ mf if self._unit_weights else (mf * left[:, :1]).T @ mf
        return _whitened_loss(self._sw, self._mean_f, self._w_f, s_m, s_fm, s_mm)

    def _compiled(self, frame: Frame, *, merge: bool) -> float:
        """The loss of the material channels (one indicator per material, k_a, k_d * normal),
        or with ``merge`` of :func:`normal_channels` (every material taken as one), in one
        compiled pass (:func:`vehicle_pose.loss.moments.frame_loss`)."""
        return frame_loss(frame.labels, frame.attrs, self._fw, self._w, unit_weights=self._unit_weights,
                          x0=frame.x0, y0=frame.y0, width=frame.width, kinds=frame.n_parts, merge=merge,
                          min_pixels=self.min_pixels, sw=self._sw, mean_f=self._mean_f, w_f=self._w_f, rtol=_RTOL)


class PartsInvariantLoss(InvariantLoss):
    """The invariant loss on :func:`part_channels`, with the moments gathered per material.

    Equal to ``InvariantLoss(target, channels=part_channels)`` (to rounding), but no (N, m)
    channel matrix is built: the moments of the one-hot material channels are label counts
    and per-label sums, gathered in one compiled pass (:mod:`vehicle_pose.loss.moments`).
    """

    name = "invariant-parts"

    def __init__(self, target: PhotoTarget, *, min_pixels: int = 16) -> None:
        super().__init__(target, channels=part_channels, min_pixels=min_pixels)

    @timed("loss")
    def __call__(self, frame: Frame) -> float:
        return self._compiled(frame, merge=False)
