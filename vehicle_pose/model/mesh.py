"""Render-ready meshes: material parts, levels of detail and their outlines.

A :class:`Mesh` is a tuple of :class:`Part` in the mesh file's own coordinates (scene
transforms applied, see :mod:`vehicle_pose.model.loading`). A part knows its material kind
(body, glass, tyre, wheel, light, other), its albedo (material colour, vertex colours) and,
where the file has one, its texture.
"""

from __future__ import annotations

import functools
import itertools
import logging
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np
import numpy.typing as npt

from vehicle_pose.errors import EmptyMeshError
from vehicle_pose.model.progressive import Progressive, merged_vertices

# trimesh, cv2 and fast_simplification are imported where they are used: a process that only
# reads prepared models (vehicle_pose.model.store) never needs them.

__all__ = ["KINDS", "Part", "Mesh", "classify_part", "column_bounds", "LUMA"]

log = logging.getLogger(__name__)

KINDS: tuple[str, ...] = ("body", "glass", "tyre", "wheel", "light", "other")
_KEYWORDS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("glass", ("glass", "window", "windshield", "windscreen", "glazing")),
    ("tyre", ("tyre", "tire", "rubber")),
    ("wheel", ("wheel", "rim", "hub")),
    ("light", ("light", "lamp", "headl", "taill", "indicator")),
    ("other", ("interior", "seat", "dashboard", "steering")),
)
LUMA = np.array([0.299, 0.587, 0.114])
_uid = itertools.count(1)
_SIMPLIFY_LOCK = threading.Lock()
_OUTLINE_LOCK = threading.Lock()


def classify_part(*names: str | None) -> str:
    """Material kind of a part from its geometry and material names; 'body' when none match."""
    text = " ".join(n.lower() for n in names if n)
    for kind, words in _KEYWORDS:
        if any(w in text for w in words):
            return kind
    return "body"


def column_bounds(points: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """The least and the largest of each column of (N, 3) points, (2, 3): column by column, the
    same values as a reduction across the rows in a tenth of its time on millions of points."""
    return np.array([[points[:, k].min() for k in range(3)], [points[:, k].max() for k in range(3)]])


@dataclass(frozen=True, eq=False)
class Part:
    """One material group of a mesh, ready for rendering.

    Attributes
    ----------
    vertices : (V, 3) float64, mesh units, mesh frame
    normals : (V, 3) float32, unit, mesh frame (sign is irrelevant)
    faces : (F, 3) uint32
    uv : (V, 2) float32 or None
    albedo : (V,) float32, gray reflectance in [0, 1]
    texture : (h, w, 3) uint8 or None, multiplies the albedo
    one_sided : bool
        Every face is wound so that the side seen from outside the model faces the camera
        (set by :func:`vehicle_pose.render.exterior.exterior_faces`, which found no view that sees
        its other side): the renderer culls these faces from behind. Otherwise (the default,
        for meshes as loaded, whose winding is often inconsistent) both sides are drawn.
    """

    name: str
    kind: str
    vertices: npt.NDArray[np.float64]
    normals: npt.NDArray[np.float32]
    faces: npt.NDArray[np.uint32]
    albedo: npt.NDArray[np.float32]
    uv: npt.NDArray[np.float32] | None = None
    texture: npt.NDArray[np.uint8] | None = None
    one_sided: bool = False

    @property
    def label(self) -> int:
        """1-based index of the part's kind in :data:`KINDS` (0 is background)."""
        return KINDS.index(self.kind) + 1


@dataclass(frozen=True, eq=False)
class Mesh:
    """A vehicle mesh as a list of parts; ``key`` identifies it for GPU buffer caches."""

    parts: tuple[Part, ...]
    source: str = ""
    key: int = field(default_factory=lambda: next(_uid))

    def __post_init__(self) -> None:
        if self.n_faces == 0:
            raise EmptyMeshError(f"mesh {self.source or '(in memory)'} has no faces")

    @property
    def n_faces(self) -> int:
        return int(sum(len(p.faces) for p in self.parts))

    @property
    def n_vertices(self) -> int:
        return int(sum(len(p.vertices) for p in self.parts))

    @cached_property
    def vertices(self) -> npt.NDArray[np.float64]:
        """All vertices (N, 3), mesh frame."""
        return np.concatenate([p.vertices for p in self.parts])

    @cached_property
    def bounds(self) -> npt.NDArray[np.float64]:
        """Axis-aligned bounds (2, 3): min and max corner."""
        return column_bounds(self.vertices)

    @cached_property
    def box_corners(self) -> npt.NDArray[np.float64]:
        """The 8 corners (8, 3) of the axis-aligned bounding box."""
        lo, hi = self.bounds
        return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])

    @cached_property
    def sphere(self) -> tuple[npt.NDArray[np.float64], float]:
        """Centre (3,) and radius of a sphere enclosing the mesh."""
        lo, hi = self.bounds
        centre = 0.5 * (lo + hi)
        d = [self.vertices[:, k] - centre[k] for k in range(3)]
        # The largest squared distance, summed in the order np.linalg.norm sums it, then its
        # root: the same radius bit for bit, without a reduction across the rows.
        return centre, float(np.sqrt((d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).max()))

    def sample_points(self, count: int = 2000, seed: int = 0) -> npt.NDArray[np.float64]:
        """Up to ``count`` vertices (N, 3) chosen at random, for error metrics."""
        v = self.vertices
        if len(v) <= count:
            return v
        return v[np.random.default_rng(seed).choice(len(v), count, replace=False)]

    def extreme_points(self, count: int = 2000, seed: int = 0) -> npt.NDArray[np.float64]:
        """The points of :meth:`sample_points` that can bound a projection of them: the vertices
        of their convex hull (N, 3), in the samples' order; kept per ``count`` and ``seed``.

        A camera projects a point to ``u = a.p / c.p``, a linear-fractional function, whose
        largest and smallest values over a convex polytope in front of the camera lie at its
        vertices; and a sample lies behind the camera exactly when a vertex does (the depth is
        linear). So the box of the samples' projection, and whether it exists, is the same
        computed from these points: 40-80 of 1000 for a car, a fraction of the cost for the
        searches that fit a camera to a box at every sample.
        """
        cache: dict[tuple[int, int], npt.NDArray[np.float64]] = self.__dict__.setdefault("_extreme", {})
        points = cache.get((count, seed))
        if points is None:
            from scipy.spatial import ConvexHull, QhullError

            samples = self.sample_points(count, seed)
            try:
                points = samples[np.sort(ConvexHull(samples).vertices)]
            except (QhullError, ValueError):  # flat or too few samples: no hull to stand for them
                points = samples
            cache[(count, seed)] = points
        return points

    def decimated(self, max_faces: int) -> Mesh:
        """A coarser copy with at most about ``max_faces`` faces; textures folded into albedo.

        The budget is shared so that small parts (wheels, lights) stay whole and the large ones
        (the body) give up the faces: one ratio for every part reduced a 160-face wheel to 2
        faces. Coincident vertices are merged first: CAD meshes often come as triangle soups
        (or are split along creases for shading), and a quadric simplifier cannot collapse the
        edges of a soup without tearing holes in it.
        """
        if self.n_faces <= max_faces:
            return self
        import trimesh

        from vehicle_pose.model.loading import shading_geometry

        budgets = _share_faces([len(p.faces) for p in self.parts], max_faces)
        parts = []
        for p, budget in zip(self.parts, budgets, strict=True):
            albedo = _mean_albedo(p)
            if budget >= len(p.faces) or len(p.faces) < 64:
                parts.append(replace(p, uv=None, texture=None, albedo=np.full(len(p.vertices), albedo, np.float32)))
                continue
            progressive = self._progressive(p)
            # the count fast_simplification.simplify(target_reduction=1 - budget / faces) aims at
            target = int((1 - (1.0 - budget / len(p.faces))) * len(progressive.faces))
            pts, tris = progressive.level(target)
            if len(tris) == 0:
                continue
            tm = trimesh.Trimesh(pts, tris, process=False)
            verts, normals, faces = shading_geometry(tm)
            parts.append(
                Part(p.name, p.kind, verts, normals, faces, np.full(len(verts), albedo, np.float32))
            )
        return Mesh(tuple(parts), source=f"{self.source} (decimated to {max_faces})")

    def _progressive(self, part: Part) -> Progressive:
        """The part's simplification (coincident vertices merged first), run once for every
        level (:mod:`vehicle_pose.model.progressive`)."""
        with _SIMPLIFY_LOCK:  # the simplifier keeps its mesh in global state
            cache: dict[int, Progressive] = self.__dict__.setdefault("_progressive_cache", {})
            found = cache.get(id(part))
            if found is None:
                found = cache[id(part)] = Progressive(*merged_vertices(part.vertices, part.faces))
            return found

    def forget_simplification(self) -> None:
        """Drop the parts' simplification records (for a 2M-face mesh about 100 MB); a later
        level runs the simplifier again."""
        self.__dict__.pop("_progressive_cache", None)

    def outlines(self, size: int = 256,
                 frame: tuple[npt.NDArray[np.float64], float] | None = None) -> npt.NDArray[np.bool_]:
        """Orthographic silhouettes (14, size, size) along the 6 axes and 8 diagonals.

        Drawn on the CPU (no OpenGL) within ``frame`` = (centre, radius), the mesh's enclosing
        sphere by default; :meth:`outline_agreement` compares two meshes on the same frame.
        """
        centre, radius = self.sphere if frame is None else frame
        dirs = [np.eye(3)[i] * s for i in range(3) for s in (1.0, -1.0)]
        dirs += [np.array(d) / np.sqrt(3.0) for d in itertools.product((1.0, -1.0), repeat=3)]
        verts = self.vertices - centre
        offsets = np.cumsum([0] + [len(p.vertices) for p in self.parts])
        faces = np.concatenate([p.faces.astype(np.int64) + o for p, o in zip(self.parts, offsets[:-1], strict=True)])
        out = np.zeros((len(dirs), size, size), np.uint8)
        shift = 4
        scale = (size / 2.0) / radius * (1 << shift)
        one = 1 << shift
        for k, d in enumerate(dirs):
            a = np.cross(d, [0.0, 0.0, 1.0] if abs(d[2]) < 0.9 else [1.0, 0.0, 0.0])
            a /= np.linalg.norm(a)
            b = np.cross(d, a)
            uv = np.empty((len(verts), 2), np.int32)
            for column, axis in enumerate((a, b)):
                uv[:, column] = np.round((verts @ axis) * scale + (size / 2.0) * one)
            # Triangles under a pixel mark the pixels of their corners (a dense mesh has
            # millions); the others are filled one call each, as fillPoly on many polygons
            # fills their overlaps even-odd.
            large = _compiled_mark_small()(uv, faces, out[k], shift)
            tris = uv[faces[large]]
            _fill_triangles(out[k], tris, tris.min(axis=1), tris.max(axis=1), shift)
        return out.astype(bool)

    @property
    def reference_outlines(self) -> npt.NDArray[np.bool_]:
        """:meth:`outlines` at 256 pixels, which :meth:`outline_agreement` compares levels of
        detail with: drawn once, by the first thread to ask (the others wait for it)."""
        with _OUTLINE_LOCK:
            found = self.__dict__.get("_reference_outlines")
            if found is None:
                found = self.__dict__["_reference_outlines"] = self.outlines(256)
            return found

    def outline_agreement(self, other: Mesh, size: int = 256) -> float:
        """The lowest IoU of the two meshes' :meth:`outlines` over the 14 directions."""
        a = self.reference_outlines if size == 256 else self.outlines(size)
        b = other.outlines(size, frame=self.sphere)
        inter = (a & b).sum(axis=(1, 2))
        union = np.maximum((a | b).sum(axis=(1, 2)), 1)
        return float((inter / union).min())


def _mark_small(uv: npt.NDArray[np.int32], faces: npt.NDArray[np.int64], image: npt.NDArray[np.uint8],
                shift: int) -> npt.NDArray[np.int64]:
    """Set the pixels of the corners of the triangles spanning less than a pixel along both
    axes (``uv`` fixed point with ``shift`` bits, clipped to the image); the others' indices."""
    one = 1 << shift
    size_y, size_x = image.shape
    large = np.empty(len(faces), np.int64)
    n = 0
    for f in range(len(faces)):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        xa, xb, xc, ya, yb, yc = uv[a, 0], uv[b, 0], uv[c, 0], uv[a, 1], uv[b, 1], uv[c, 1]
        if max(xa, xb, xc) - min(xa, xb, xc) < one and max(ya, yb, yc) - min(ya, yb, yc) < one:
            for v in (a, b, c):
                image[min(max(uv[v, 1] >> shift, 0), size_y - 1), min(max(uv[v, 0] >> shift, 0), size_x - 1)] = 1
        else:
            large[n] = f
            n += 1
    return large[:n]


@functools.cache
def _compiled_mark_small() -> Callable[..., npt.NDArray[np.int64]]:
    """:func:`_mark_small` compiled by numba (imported only when outlines are drawn)."""
    from numba import njit

    return njit(cache=True, nogil=True)(_mark_small)


def _fill_triangles(image: npt.NDArray[np.uint8], tris: npt.NDArray[np.int32],
                    lo: npt.NDArray[np.int32], hi: npt.NDArray[np.int32], shift: int) -> None:
    """Fill triangles ``tris`` (T, 3, 2), fixed point with ``shift`` bits, into ``image`` with 1
    (``lo``, ``hi``: their corners' bounds).

    A triangle whose pixels are all set already changes nothing, so the largest are drawn
    first and, between batches, those whose corners' box (widened by a pixel, which holds
    every pixel cv2.fillConvexPoly may touch) is already full are skipped: the image is the
    one drawing every triangle gives, with a fraction of the calls where the surfaces overlap.
    """
    import cv2

    size_y, size_x = image.shape
    one = 1 << shift
    x0 = np.clip((lo[:, 0] >> shift) - 1, 0, size_x)
    x1 = np.clip(((hi[:, 0] + one - 1) >> shift) + 2, 0, size_x)
    y0 = np.clip((lo[:, 1] >> shift) - 1, 0, size_y)
    y1 = np.clip(((hi[:, 1] + one - 1) >> shift) + 2, 0, size_y)
    area = (hi[:, 0] - lo[:, 0]).astype(np.int64) * (hi[:, 1] - lo[:, 1])
    which = np.argsort(-area, kind="stable")
    x0, x1, y0, y1 = x0[which], x1[which], y0[which], y1[which]
    batch = 512
    while len(which):
        for t in which[:batch]:
            cv2.fillConvexPoly(image, tris[t], 1, cv2.LINE_8, shift)
        which, x0, x1, y0, y1 = which[batch:], x0[batch:], x1[batch:], y0[batch:], y1[batch:]
        if len(which):
            s = cv2.integral(image)
            full = s[y1, x1] - s[y0, x1] - s[y1, x0] + s[y0, x0] == (y1 - y0) * (x1 - x0)
            which, x0, x1, y0, y1 = which[~full], x0[~full], x1[~full], y0[~full], y1[~full]
            batch *= 2


def _share_faces(sizes: Sequence[int], budget: int) -> list[int]:
    """Faces allowed to each part: an equal share of ``budget``, where a part needs less its
    own count and the rest shared among the larger parts."""
    out = [0] * len(sizes)
    left, remaining = len(sizes), float(budget)
    for i in sorted(range(len(sizes)), key=lambda i: sizes[i]):
        out[i] = int(min(sizes[i], remaining / left))
        remaining -= out[i]
        left -= 1
    return out


def _mean_albedo(part: Part) -> float:
    base = float(part.albedo.mean()) if part.albedo.size else 1.0
    if part.texture is None:
        return base
    return base * float((part.texture.reshape(-1, 3) @ LUMA).mean() / 255.0)
