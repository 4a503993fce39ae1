"""Compiled per-pixel moment sums and the invariant loss from them (numba).

The loss needs, over the pixels a rendered model covers, the sums of the photo attributes F
and of the model attributes M and of their products (method.md §2). With NumPy that is a
chain of gathers, casts and small matrix products, each a pass over memory; this kernel makes
one pass over the read-back window and accumulates everything in float64, and agrees with the
NumPy path to rounding (tests/loss/test_moments.py). :func:`frame_loss` goes on to the loss
itself in the same compiled call: assembled in NumPy, the covariances and their
eigen-decomposition cost as much as the pass over the pixels
(docs/decisions/0010-rendering-costs.md).

Compiled on first use and cached beside this file (``NUMBA_CACHE_DIR`` moves the cache).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
import numpy.typing as npt
from numba import njit

__all__ = ["PartMoments", "part_moments", "frame_loss", "warm_up"]

FloatArray = npt.NDArray[np.float64]
Array = npt.NDArray[Any]


class PartMoments(NamedTuple):
    """Weighted sums per material label (rows: labels 1..k) and over all covered pixels.

    ``weight`` (k,) the summed weight, ``f`` (k, n) the summed weighted photo attributes, ``a``
    (k, 4) the summed weighted model attributes, ``fa`` (n, 4) sum of weighted F times M, and
    ``aa`` (4, 4) sum of weighted M M^T; ``pixels`` the number of covered pixels.
    """

    pixels: int
    weight: FloatArray
    f: FloatArray
    a: FloatArray
    fa: FloatArray
    aa: FloatArray


@njit(cache=True, nogil=True)
def _part_moments(labels: Array, attrs: Array, fw: Array, w: Array, unit: bool, x0: int, y0: int, width: int,
                  k: int) -> tuple[int, Array, Array, Array, Array, Array]:  # pragma: no cover - compiled
    h, wd = labels.shape
    n = fw.shape[1]
    cnt = np.zeros(k + 1)
    sf = np.zeros((k + 1, n))
    sa = np.zeros((k + 1, 4))
    sfa = np.zeros((n, 4))
    saa = np.zeros((4, 4))
    a = np.zeros(4)
    pixels = 0
    for r in range(h):
        base = (r + y0) * width + x0
        for c in range(wd):
            lab = labels[r, c]
            if lab == 0:
                continue
            if lab > k:
                raise ValueError("a label beyond the material kinds")
            p = base + c
            pixels += 1
            for j in range(4):
                a[j] = attrs[r, c, j]
            wt = 1.0 if unit else w[p]
            cnt[lab] += wt
            for i in range(n):
                f = fw[p, i]
                sf[lab, i] += f
                for j in range(4):
                    sfa[i, j] += f * a[j]
            for j in range(4):
                aj = wt * a[j]
                sa[lab, j] += aj
                for q in range(j, 4):
                    saa[j, q] += aj * a[q]
    for j in range(4):
        for q in range(j):
            saa[j, q] = saa[q, j]
    return pixels, cnt[1:], sf[1:], sa[1:], sfa, saa


@njit(cache=True, nogil=True)
def _loss_of_parts(sw: float, mean_f: Array, w_f: Array, count: Array, f: Array, a: Array, fa: Array, aa: Array,
                   rtol: float) -> float:  # pragma: no cover - compiled
    """The loss of M = (one indicator per material, k_a, k_d * normal) from per-material sums."""
    k, n = count.shape[0], mean_f.shape[0]
    m = k + 4
    worst = float(min(n, m))
    if sw <= 0.0 or w_f.shape[1] == 0:
        return worst
    mean_m = np.empty(m)
    for i in range(k):
        mean_m[i] = count[i] / sw
    for j in range(4):
        t = 0.0
        for i in range(k):
            t += a[i, j]
        mean_m[k + j] = t / sw
    c_mm = np.empty((m, m))
    for i in range(k):
        for q in range(k):
            c_mm[i, q] = (count[i] / sw if i == q else 0.0) - mean_m[i] * mean_m[q]
        for j in range(4):
            c_mm[i, k + j] = a[i, j] / sw - mean_m[i] * mean_m[k + j]
            c_mm[k + j, i] = c_mm[i, k + j]
    for j in range(4):
        for q in range(4):
            c_mm[k + j, k + q] = aa[j, q] / sw - mean_m[k + j] * mean_m[k + q]
    c_fm = np.empty((n, m))
    for p in range(n):
        for i in range(k):
            c_fm[p, i] = f[i, p] / sw - mean_f[p] * mean_m[i]
        for j in range(4):
            c_fm[p, k + j] = fa[p, j] / sw - mean_f[p] * mean_m[k + j]
    if not (np.all(np.isfinite(c_mm)) and np.all(np.isfinite(c_fm))):
        return worst
    evals, evecs = np.linalg.eigh(c_mm)
    top = evals[-1]
    if not np.isfinite(top) or top <= 0.0:
        return worst
    # sum over the kept directions v of |W_F^T C_FM v|^2 / lambda: the squared canonical
    # correlations (directions without variance carry no information and are dropped).
    proj = w_f.T @ c_fm
    explained = 0.0
    for j in range(m):
        if evals[j] > rtol * top:
            for r in range(proj.shape[0]):
                t = 0.0
                for q in range(m):
                    t += proj[r, q] * evecs[q, j]
                explained += t * t / evals[j]
    return min(max(worst - explained, 0.0), worst)


@njit(cache=True, nogil=True)
def _frame_loss(labels: Array, attrs: Array, fw: Array, w: Array, unit: bool, x0: int, y0: int, width: int, k: int,
                merge: bool, min_pixels: int, sw: float, mean_f: Array, w_f: Array,
                rtol: float) -> float:  # pragma: no cover - compiled
    pixels, cnt, sf, sa, sfa, saa = _part_moments(labels, attrs, fw, w, unit, x0, y0, width, k)
    if merge:
        one = np.empty(1)
        one[0] = cnt.sum()
        sf1 = np.empty((1, sf.shape[1]))
        for i in range(sf.shape[1]):
            sf1[0, i] = sf[:, i].sum()
        sa1 = np.empty((1, 4))
        for j in range(4):
            sa1[0, j] = sa[:, j].sum()
        cnt, sf, sa = one, sf1, sa1
    if pixels < min_pixels:
        return float(min(mean_f.shape[0], cnt.shape[0] + 4))
    return _loss_of_parts(sw, mean_f, w_f, cnt, sf, sa, sfa, saa, rtol)


def frame_loss(
    labels: npt.NDArray[np.uint8],
    attrs: npt.NDArray[np.float32],
    fw: FloatArray,
    w: FloatArray,
    *,
    unit_weights: bool,
    x0: int,
    y0: int,
    width: int,
    kinds: int,
    merge: bool,
    min_pixels: int,
    sw: float,
    mean_f: FloatArray,
    w_f: FloatArray,
    rtol: float,
) -> float:
    """The invariant loss of a rendered window, in one compiled call.

    The model attributes are one indicator per material kind and (k_a, k_d * normal); with
    ``merge`` the materials are taken as one (the coverage indicator). Arguments as for
    :func:`part_moments`, plus the photo's total weight ``sw``, mean ``mean_f`` and whitening
    ``w_f`` (``W_F^T C_FF W_F = I`` over the range of C_FF, (n, r)) and the relative eigenvalue
    ``rtol`` under which a model
    covariance direction counts as empty. Fewer than ``min_pixels`` covered pixels score the
    maximum, ``min(n, m)``.
    """
    return float(_frame_loss(labels, attrs, fw, w, bool(unit_weights), int(x0), int(y0), int(width), int(kinds),
                             bool(merge), int(min_pixels), float(sw), mean_f, w_f, float(rtol)))


def part_moments(
    labels: npt.NDArray[np.uint8],
    attrs: npt.NDArray[np.float32],
    fw: FloatArray,
    w: FloatArray,
    *,
    unit_weights: bool,
    x0: int,
    y0: int,
    width: int,
    kinds: int,
) -> PartMoments:
    """Moments of a rendered window against a photo.

    Parameters
    ----------
    labels : (h, w) uint8
        Material label + 1 per window pixel, 0 where the model is absent; at most ``kinds``.
    attrs : (h, w, 4) float32
        Model attributes per window pixel.
    fw : (H * W, n) float64
        Photo attributes times the pixel weights, whole image, row-major.
    w : (H * W,) float64
        Pixel weights (read only when ``unit_weights`` is false).
    x0, y0, width : int
        The window's top-left pixel in the image and the image's width.

    Raises
    ------
    ValueError
        A label is above ``kinds``.
    """
    return PartMoments(*_part_moments(labels, attrs, fw, w, bool(unit_weights), int(x0), int(y0), int(width),
                                      int(kinds)))


def warm_up() -> None:
    """Compile (or load from the cache) the kernel for the array types the renderer produces:
    read-only float32 attributes and uint8 labels from the read-back buffers. The Docker image
    calls this at build time, so that its cache ships inside the image."""
    attrs = np.frombuffer(bytes(16), np.float32).reshape(1, 1, 4)
    labels = np.frombuffer(bytes([1]), np.uint8).reshape(1, 1)
    part_moments(labels, attrs, np.zeros((1, 1)), np.ones(1), unit_weights=True, x0=0, y0=0, width=1, kinds=1)
    frame_loss(labels, attrs, np.zeros((1, 1)), np.ones(1), unit_weights=True, x0=0, y0=0, width=1, kinds=1,
               merge=False, min_pixels=16, sw=1.0, mean_f=np.zeros(1), w_f=np.ones((1, 1)), rtol=1e-12)
