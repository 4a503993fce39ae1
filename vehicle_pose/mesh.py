"""Loading vehicle meshes (OBJ, PLY, OFF, STL, GLB/GLTF) into render-ready parts.

Every geometry of the file becomes a :class:`Part` in the mesh file's own coordinates (scene
transforms applied). A part knows its material kind (body, glass, tyre, wheel, light, other),
guessed from geometry and material names, its albedo (material colour, vertex colours) and,
where the file has one, its texture. Shading normals survive inconsistent face winding: the
winding is repaired where the surface is connected, and parts that stay inconsistent are
flat-shaded; the renderer turns every normal towards the camera.
"""

from __future__ import annotations

import itertools
import logging
import threading
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt
from numba import njit

from .errors import EmptyMeshError, ModelError

if TYPE_CHECKING:
    import trimesh

# trimesh, cv2 and fast_simplification are imported where they are used: a process that only
# reads prepared models (vehicle_pose.store) never needs them.

__all__ = ["KINDS", "Part", "Mesh", "load_mesh", "load_mesh_recording", "classify_part"]

log = logging.getLogger(__name__)

KINDS: tuple[str, ...] = ("body", "glass", "tyre", "wheel", "light", "other")
_KEYWORDS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("glass", ("glass", "window", "windshield", "windscreen", "glazing")),
    ("tyre", ("tyre", "tire", "rubber")),
    ("wheel", ("wheel", "rim", "hub")),
    ("light", ("light", "lamp", "headl", "taill", "indicator")),
    ("other", ("interior", "seat", "dashboard", "steering")),
)
_LUMA = np.array([0.299, 0.587, 0.114])
_uid = itertools.count(1)
_CREASE = np.radians(35.0)
_SIMPLIFY_LOCK = threading.Lock()


def classify_part(*names: str | None) -> str:
    """Material kind of a part from its geometry and material names; 'body' when none match."""
    text = " ".join(n.lower() for n in names if n)
    for kind, words in _KEYWORDS:
        if any(w in text for w in words):
            return kind
    return "body"


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
        (set by :meth:`vehicle_pose.render.Renderer.exterior`, which found no view that sees
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
        v = self.vertices
        return np.stack([v.min(0), v.max(0)])

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
        return centre, float(np.linalg.norm(self.vertices - centre, axis=1).max())

    def sample_points(self, count: int = 2000, seed: int = 0) -> npt.NDArray[np.float64]:
        """Up to ``count`` vertices (N, 3) chosen at random, for error metrics."""
        v = self.vertices
        if len(v) <= count:
            return v
        return v[np.random.default_rng(seed).choice(len(v), count, replace=False)]

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
        import fast_simplification
        import trimesh

        budgets = _share_faces([len(p.faces) for p in self.parts], max_faces)
        parts = []
        for p, budget in zip(self.parts, budgets):
            albedo = _mean_albedo(p)
            if budget >= len(p.faces) or len(p.faces) < 64:
                parts.append(replace(p, uv=None, texture=None, albedo=np.full(len(p.vertices), albedo, np.float32)))
                continue
            merged_vertices, merged_faces = self._merged(p)
            with _SIMPLIFY_LOCK:  # the simplifier keeps its mesh in global state
                pts, tris = fast_simplification.simplify(
                    merged_vertices, merged_faces, target_reduction=1.0 - budget / len(p.faces),
                )
            if len(tris) == 0:
                continue
            tm = trimesh.Trimesh(pts, tris, process=False)
            verts, normals, faces = _shading_geometry(tm)
            parts.append(
                Part(p.name, p.kind, verts, normals, faces, np.full(len(verts), albedo, np.float32))
            )
        return Mesh(tuple(parts), source=f"{self.source} (decimated to {max_faces})")

    def _merged(self, part: Part) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.int64]]:
        """The part's vertices and faces with coincident vertices merged, kept for the next
        level's decimation (0.6 s a level for a 2M-face mesh)."""
        cache: dict[int, tuple[npt.NDArray[np.float64], npt.NDArray[np.int64]]] = self.__dict__.setdefault("_merged_cache", {})
        found = cache.get(id(part))
        if found is None:
            import trimesh

            merged = trimesh.Trimesh(part.vertices, part.faces, process=True)
            found = cache[id(part)] = (np.asarray(merged.vertices, np.float64), np.asarray(merged.faces, np.int64))
        return found

    def outlines(self, size: int = 256, frame: tuple[npt.NDArray[np.float64], float] | None = None) -> npt.NDArray[np.bool_]:
        """Orthographic silhouettes (14, size, size) along the 6 axes and 8 diagonals.

        Drawn on the CPU (no OpenGL) within ``frame`` = (centre, radius), the mesh's enclosing
        sphere by default; :meth:`outline_agreement` compares two meshes on the same frame.
        """
        import cv2

        centre, radius = self.sphere if frame is None else frame
        dirs = [np.eye(3)[i] * s for i in range(3) for s in (1.0, -1.0)]
        dirs += [np.array(d) / np.sqrt(3.0) for d in itertools.product((1.0, -1.0), repeat=3)]
        verts = self.vertices - centre
        offsets = np.cumsum([0] + [len(p.vertices) for p in self.parts])
        faces = np.concatenate([p.faces.astype(np.int64) + o for p, o in zip(self.parts, offsets)])
        out = np.zeros((len(dirs), size, size), np.uint8)
        shift = 4
        scale = (size / 2.0) / radius * (1 << shift)
        one = 1 << shift
        for k, d in enumerate(dirs):
            a = np.cross(d, [0.0, 0.0, 1.0] if abs(d[2]) < 0.9 else [1.0, 0.0, 0.0])
            a /= np.linalg.norm(a)
            b = np.cross(d, a)
            uv = np.stack([verts @ a, verts @ b], axis=1) * scale + (size / 2.0) * one
            tris = np.round(uv[faces]).astype(np.int32)
            extent = tris.max(axis=1) - tris.min(axis=1)
            small = extent.max(axis=1) < one
            # Triangles under a pixel mark the pixels of their corners (a dense mesh has
            # millions); the others are filled one call each, as fillPoly on many polygons
            # fills their overlaps even-odd.
            px = np.clip(tris[small].reshape(-1, 2) >> shift, 0, size - 1)
            out[k][px[:, 1], px[:, 0]] = 1
            for tri in tris[~small]:
                cv2.fillConvexPoly(out[k], tri, 1, cv2.LINE_8, shift)
        return out.astype(bool)

    @cached_property
    def _outlines(self) -> npt.NDArray[np.bool_]:
        return self.outlines(256)

    def outline_agreement(self, other: Mesh, size: int = 256) -> float:
        """The lowest IoU of the two meshes' :meth:`outlines` over the 14 directions."""
        a = self._outlines if size == 256 else self.outlines(size)
        b = other.outlines(size, frame=self.sphere)
        inter = (a & b).sum(axis=(1, 2))
        union = np.maximum((a | b).sum(axis=(1, 2)), 1)
        return float((inter / union).min())


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
    return base * float((part.texture.reshape(-1, 3) @ _LUMA).mean() / 255.0)


def _resolver(mesh_path: Path, extra_dirs: Sequence[Path]) -> Any:
    """A trimesh resolver that finds texture files by relative path, then by base name in
    extra folders, and records what it read (``read``) and what it could not find (``missing``)."""
    import trimesh

    class SearchResolver(trimesh.resolvers.FilePathResolver):  # type: ignore[misc]
        def __init__(self) -> None:
            super().__init__(str(mesh_path))
            self._dirs = [mesh_path.parent, *extra_dirs]
            self.read: list[Path] = []
            self.missing: list[str] = []

        def get(self, name: str) -> bytes:
            found = _find(self._dirs, name)
            if found is None:
                self.missing.append(name)
                raise FileNotFoundError(name)
            self.read.append(found.resolve())
            return found.read_bytes()

    return SearchResolver()


def _find(dirs: Sequence[Path], name: str) -> Path | None:
    base = name.replace("\\", "/").split("/")[-1]
    candidates = [d / name for d in dirs[:1]] + [d / base for d in dirs]
    for c in candidates:
        if c.is_file():
            return c
    for d in dirs:
        if d.is_dir():
            for f in d.iterdir():
                if f.name.lower() == base.lower() and f.is_file():
                    return f
    return None


def resolves(mesh_path: Path, extra_dirs: Sequence[Path], name: str) -> bool:
    """Whether a file the mesh names (``name``) is found now."""
    return _find([mesh_path.parent, *extra_dirs], name) is not None


def _shading_geometry(
    tm: trimesh.Trimesh,
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float32], npt.NDArray[np.uint32]]:
    """Vertices, unit normals and faces; flat-shaded when the winding cannot be made consistent."""
    import trimesh

    if not tm.is_winding_consistent:
        tm = trimesh.Trimesh(tm.vertices, _oriented(tm.faces), process=False)
    if tm.is_winding_consistent:
        # Split vertices along creases sharper than _CREASE so panels keep their own normals.
        smooth = trimesh.graph.smooth_shade(tm, angle=_CREASE)
        normals = np.asarray(smooth.vertex_normals, dtype=np.float32)
        return np.asarray(smooth.vertices, np.float64), normals, np.asarray(smooth.faces, np.uint32)
    faces = np.asarray(tm.faces)
    verts = np.asarray(tm.vertices, np.float64)[faces.reshape(-1)]
    normals = np.repeat(np.asarray(tm.face_normals, np.float32), 3, axis=0)
    return verts, normals, np.arange(len(verts), dtype=np.uint32).reshape(-1, 3)


@njit(cache=True)
def _propagate(order: npt.NDArray[np.int64], pred: npt.NDArray[np.int64], inc: npt.NDArray[np.bool_],
               n: int) -> npt.NDArray[np.bool_]:
    """Flip of each face: its parent's, changed where their shared edge runs the same way."""
    flip = np.zeros(n, np.bool_)
    for i in order:
        p = pred[i]
        if p >= 0 and p < n:
            flip[i] = flip[p] ^ inc[i]
    return flip


def _oriented(faces: npt.NDArray[np.integer]) -> npt.NDArray[np.int64]:
    """Faces wound consistently over each connected surface, as trimesh's ``fix_winding``
    does (breadth-first from one face of each component, a face flipped when the edge it shares
    with its parent runs the same way in both), in array passes instead of one Python step per
    face pair: 0.5 s instead of 35 s for a 370 000-face body. Faces meet along edges shared by
    exactly two faces; the first face of a component keeps its winding."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order, connected_components

    faces = np.asarray(faces, np.int64)
    F = len(faces)
    e = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    fid = np.repeat(np.arange(F), 3)
    lo, hi = e.min(1), e.max(1)
    fwd = e[:, 0] < e[:, 1]
    key = lo * (int(faces.max()) + 1) + hi
    order = np.argsort(key, kind="stable")
    k = key[order]
    start = np.r_[0, np.flatnonzero(np.diff(k)) + 1]
    counts = np.diff(np.r_[start, len(k)])
    two = start[counts == 2]
    a, b = order[two], order[two + 1]
    fa, fb, same = fid[a], fid[b], fwd[a] == fwd[b]
    keep = fa != fb
    fa, fb, same = fa[keep], fb[keep], same[keep]
    # one flag per face pair (two faces sharing two edges keep the first)
    pk = np.minimum(fa, fb) * F + np.maximum(fa, fb)
    _, first = np.unique(pk, return_index=True)
    fa, fb, same = fa[first], fb[first], same[first]
    adj = coo_matrix((np.ones(len(fa)), (fa, fb)), shape=(F, F))
    n_comp, labels = connected_components(adj, directed=False)
    roots = np.full(n_comp, F, np.int64)
    np.minimum.at(roots, labels, np.arange(F))
    # a super-root F joined to each component's first face: one breadth-first pass
    rows = np.r_[fa, fb, np.full(n_comp, F)]
    cols = np.r_[fb, fa, roots]
    g = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(F + 1, F + 1)).tocsr()
    bfs, pred = breadth_first_order(g, F, directed=True, return_predecessors=True)
    # Whether each tree edge (parent, face) joins the two faces against each other's winding.
    pair = np.r_[fa * F + fb, fb * F + fa]
    by_pair = np.argsort(pair)
    pair, flags = pair[by_pair], np.r_[same, same][by_pair]
    nodes = bfs[1:]
    p = pred[nodes]
    inc = np.zeros(F + 1, np.bool_)
    inner = p < F
    inc[nodes[inner]] = flags[np.searchsorted(pair, p[inner] * F + nodes[inner])]
    flip = _propagate(nodes, pred.astype(np.int64), inc, F)
    out = faces.copy()
    out[flip] = out[flip][:, ::-1]
    return out


def _part_from_trimesh(name: str, tm: trimesh.Trimesh) -> Part | None:
    import trimesh

    tm.remove_unreferenced_vertices()
    if len(tm.faces) == 0:
        return None
    visual = tm.visual
    material = getattr(visual, "material", None)
    mat_name = getattr(material, "name", None)
    kind = classify_part(name, mat_name)
    uv = getattr(visual, "uv", None)
    texture = None
    image = getattr(material, "image", None) if material is not None else None
    if image is None and material is not None:
        image = getattr(material, "baseColorTexture", None)
    albedo_const = _material_gray(material)
    vertex_albedo = None
    if isinstance(visual, trimesh.visual.ColorVisuals) and visual.kind in ("vertex", "face"):
        vertex_albedo = (np.asarray(visual.vertex_colors, np.float64)[:, :3] @ _LUMA / 255.0).astype(np.float32)
    if uv is not None and image is not None and len(uv) == len(tm.vertices):
        texture = np.asarray(image.convert("RGB"), dtype=np.uint8)
        uv = np.asarray(uv, np.float32)
        # Texture coordinates are per vertex; keep the file's vertices so they stay aligned.
        verts = np.asarray(tm.vertices, np.float64)
        faces = np.asarray(tm.faces, np.uint32)
        normals = np.asarray(tm.vertex_normals, np.float32)
    else:
        uv = None
        if vertex_albedo is not None:
            tm = trimesh.Trimesh(tm.vertices, tm.faces, process=False)
        verts, normals, faces = _shading_geometry(tm)
        if vertex_albedo is not None and len(vertex_albedo) != len(verts):
            vertex_albedo = None
    albedo = vertex_albedo if vertex_albedo is not None else np.full(len(verts), albedo_const, np.float32)
    return Part(name, kind, verts, normals, faces, albedo.astype(np.float32), uv, texture)


def _material_gray(material: object) -> float:
    """Gray diffuse reflectance of a trimesh material (1 when it has none)."""
    if material is None:
        return 1.0
    colour = getattr(material, "diffuse", None)
    if colour is None:
        colour = getattr(material, "baseColorFactor", None)
    if colour is None:
        return 1.0
    rgb = np.asarray(colour, np.float64).reshape(-1)[:3]
    if rgb.max() > 1.0:
        rgb = rgb / 255.0
    return float(np.clip(rgb @ _LUMA, 0.02, 1.0))


def load_mesh(path: str | Path, *, texture_dirs: Sequence[str | Path] = ()) -> Mesh:
    """Load a mesh file into parts in the file's own coordinates and units.

    Parameters
    ----------
    path : str or Path
        OBJ, PLY, OFF, STL, GLB or GLTF file.
    texture_dirs : sequence of paths, keyword-only
        Extra folders searched for texture images by base name.

    Raises
    ------
    ModelError
        The file is missing or cannot be parsed.
    EmptyMeshError
        The file holds no triangles.
    """
    return load_mesh_recording(path, texture_dirs=texture_dirs)[0]


def load_mesh_recording(path: str | Path, *, texture_dirs: Sequence[str | Path] = ()) -> tuple[Mesh, list[Path], list[str]]:
    """:func:`load_mesh`, also returning the files the mesh file led to reading (material
    libraries, textures, buffers) and the names it referred to that were not found."""
    import trimesh

    p = Path(path)
    if not p.is_file():
        raise ModelError(f"mesh file {p} does not exist")
    resolver = _resolver(p, [Path(d) for d in texture_dirs])
    try:
        scene = trimesh.load(str(p), force="scene", resolver=resolver)
    except Exception as exc:  # trimesh raises many types for malformed files
        raise ModelError(f"cannot load mesh {p.name}: {exc}") from None
    parts: list[Part] = []
    for node in scene.graph.nodes_geometry:
        transform, geom_name = scene.graph[node]
        geom = scene.geometry.get(geom_name)
        if not isinstance(geom, trimesh.Trimesh):
            continue
        tm = geom.copy()
        tm.apply_transform(transform)
        part = _part_from_trimesh(str(geom_name), tm)
        if part is not None:
            parts.append(part)
    if not parts:
        raise EmptyMeshError(f"mesh {p.name} has no faces")
    return Mesh(tuple(parts), source=str(p)), list(dict.fromkeys(resolver.read)), list(dict.fromkeys(resolver.missing))
