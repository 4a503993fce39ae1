"""Compiled per-pixel moment sums for the invariant loss (numba).

The loss needs, over the pixels a rendered model covers, the sums of the photo attributes F
and of the model attributes M and of their products (method.md §2). With NumPy that is a
chain of gathers, casts and small matrix products, each a pass over memory; this kernel makes
one pass over the read-back window and accumulates everything in float64. It is 3-4 times
faster than the NumPy path on the photoreal models (docs/benchmarks.md) and agrees with it to
rounding (tests/test_loss.py).

Compiled on first use and cached beside this file (``NUMBA_CACHE_DIR`` moves the cache).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import numpy.typing as npt
from numba import njit

__all__ = ["PartMoments", "part_moments", "warm_up"]

FloatArray = npt.NDArray[np.float64]


class PartMoments(NamedTuple):
    """Weighted sums per material label (rows: labels 1..k) and over all covered pixels.

    ``count`` (k,) the summed weight, ``f`` (k, n) the summed weighted photo attributes, ``a``
    (k, 4) the summed weighted model attributes, ``fa`` (n, 4) sum of weighted F times M, and
    ``aa`` (4, 4) sum of weighted M M^T; ``pixels`` the number of covered pixels.
    """

    pixels: int
    count: FloatArray
    f: FloatArray
    a: FloatArray
    fa: FloatArray
    aa: FloatArray


@njit(cache=True, nogil=True)
def _part_moments(labels, attrs, fw, w, unit, x0, y0, width, k):  # pragma: no cover - compiled
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
    return PartMoments(*_part_moments(labels, attrs, fw, w, bool(unit_weights), int(x0), int(y0), int(width), int(kinds)))


def warm_up() -> None:
    """Compile (or load from the cache) the kernel for the array types the renderer produces:
    read-only float32 attributes from the read-back buffer, uint8 labels. The Docker image
    calls this at build time, so that its cache ships inside the image."""
    attrs = np.frombuffer(bytes(16), np.float32).reshape(1, 1, 4)
    part_moments(np.ones((1, 1), np.uint8), attrs, np.zeros((1, 1)), np.ones(1), unit_weights=True,
                 x0=0, y0=0, width=1, kinds=1)
