"""Every level of detail of a part from one run of the quadric simplifier.

fast-simplification (Fast Quadric Mesh Simplification) collapses edges in an order that does
not depend on the target: a run to a coarse target passes through every finer one, and its
record of collapses holds them all. :class:`Progressive` runs the simplifier once, as far as it
goes, and gives any target's mesh from a prefix of that record: the same faces, in the same
order, with the same vertex positions to the last bit as a run of the simplifier to that
target (``tests/model/test_progressive.py`` checks it against the library). A 2M-face mesh's
eight levels then cost one simplification instead of eight or more (each level's outline check
may ask for another).

The positions are the simplifier's own arithmetic replayed in numpy (``Simplify.h``): each
vertex starts with the sum of the plane quadrics of its faces (summed in face order), a
collapse ``i1 -> i0`` adds the two quadrics and moves ``i0`` to the quadric's minimum, or, where
the quadric is singular or both vertices lie on a border, to the better of ``i0``, ``i1`` and
their midpoint, one collapse after another in a compiled loop (a collapse needs only earlier
collapses into its two vertices).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

__all__ = ["Progressive", "merged_vertices"]

_F64 = npt.NDArray[np.float64]
_I64 = npt.NDArray[np.int64]


def _plane_quadrics(vertices: _F64, faces: _I64) -> _F64:
    """Each vertex's sum of its faces' plane quadrics (V, 10), added face by face in order."""
    p0, p1, p2 = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    a, b = p1 - p0, p2 - p0
    n = np.stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1],
                  a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                  a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]], axis=1)
    square = np.sqrt(n[:, 0] * n[:, 0] + n[:, 1] * n[:, 1] + n[:, 2] * n[:, 2])
    with np.errstate(invalid="ignore", divide="ignore"):  # a degenerate face: NaN, as in C++
        n = n / square[:, None]
    x, y, z = n[:, 0], n[:, 1], n[:, 2]
    d = -(p0[:, 0] * x + p0[:, 1] * y + p0[:, 2] * z)
    plane = (x * x, x * y, x * z, x * d, y * y, y * z, y * d, z * z, z * d, d * d)
    # bincount adds its weights in the order given, from 0.0, as the simplifier's loop does
    corner = faces.reshape(-1)
    return np.stack([np.bincount(corner, np.repeat(c, 3), minlength=len(vertices)) for c in plane], axis=1)


def _border(n_vertices: int, faces: _I64) -> npt.NDArray[np.bool_]:
    """Vertices on an edge of one face (the simplifier's border flag)."""
    ends = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    key = np.sort(np.min(ends, axis=1) * n_vertices + np.max(ends, axis=1))
    first = np.r_[True, key[1:] != key[:-1]]
    count = np.diff(np.r_[np.flatnonzero(first), len(key)])
    once = key[first][count == 1]
    out = np.zeros(n_vertices, bool)
    out[once // n_vertices] = True
    out[once % n_vertices] = True
    uses = np.bincount(faces.reshape(-1), minlength=n_vertices)
    out[uses == 1] = True
    return out


def _walk_death_times(faces: _I64, when: _I64, into: _I64, K: int) -> _I64:
    """:meth:`Progressive._death_times`' walk: ``when[v]`` is the collapse removing vertex ``v``
    (``K``: none), ``into[v]`` the vertex it goes into."""
    death = np.full(len(faces), K, np.int64)
    for f in range(len(faces)):
        for i, j in ((0, 1), (1, 2), (2, 0)):
            x, y = faces[f, i], faces[f, j]
            while True:
                tx, ty = when[x], when[y]
                t = tx if tx < ty else ty
                if t >= K:
                    break
                if tx < ty:
                    x = into[x]
                else:
                    y = into[y]
                if x == y:
                    death[f] = min(death[f], t)
                    break
    return death


@functools.cache
def _compiled_death_times() -> Callable[..., _I64]:
    """:func:`_walk_death_times` compiled by numba."""
    from numba import njit

    return njit(cache=True, nogil=True)(_walk_death_times)


def merged_vertices(vertices: npt.ArrayLike, faces: npt.ArrayLike) -> tuple[_F64, _I64]:
    """``trimesh.Trimesh(vertices, faces, process=True)``'s vertices and faces: the vertices
    the faces use, those equal once scaled by 1e8 and rounded merged into the first of them, in
    the order they first appear; from one compiled pass with a hash table instead of trimesh's
    sort of the rows (a 4.4M-vertex soup: 0.2 s instead of 2 s). Non-finite or empty input is
    left to trimesh."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    if len(v) == 0 or len(f) == 0 or not np.isfinite(v).all():
        import trimesh

        tm = trimesh.Trimesh(v, f, process=True)
        return np.asarray(tm.vertices, np.float64), np.asarray(tm.faces, np.int64)
    referenced = np.zeros(len(v), bool)
    referenced[f] = True
    used = np.flatnonzero(referenced)
    rows = np.ascontiguousarray(np.round(v[used] * 10**8).astype(np.int64))  # trimesh's tol.merge
    first, group = _compiled_first_rows()(rows)
    inverse = np.zeros(len(v), np.int64)
    inverse[used] = group
    return v[used[first]], inverse[f.reshape(-1)].reshape(-1, 3)


def _first_rows(rows: _I64) -> tuple[_I64, _I64]:
    """For rows (n, 3): the index of the first row of each distinct value, in order, and each
    row's value's number (open addressing on a table twice the rows' count)."""
    n = len(rows)
    size = 1
    while size < 2 * n:
        size *= 2
    table = np.full(size, -1, np.int64)
    first = np.empty(n, np.int64)
    group = np.empty(n, np.int64)
    count = 0
    for r in range(n):
        h = np.uint64(rows[r, 0]) * np.uint64(0x9E3779B97F4A7C15)
        h = (h ^ (h >> np.uint64(29))) + np.uint64(rows[r, 1]) * np.uint64(0xBF58476D1CE4E5B9)
        h = (h ^ (h >> np.uint64(32))) + np.uint64(rows[r, 2]) * np.uint64(0x94D049BB133111EB)
        slot = np.int64((h ^ (h >> np.uint64(31))) & np.uint64(size - 1))
        while True:
            g = table[slot]
            if g < 0:
                table[slot] = count
                first[count] = r
                group[r] = count
                count += 1
                break
            q = first[g]
            if rows[q, 0] == rows[r, 0] and rows[q, 1] == rows[r, 1] and rows[q, 2] == rows[r, 2]:
                group[r] = g
                break
            slot = (slot + 1) & (size - 1)
    return first[:count], group


@functools.cache
def _compiled_first_rows() -> Callable[..., tuple[_I64, _I64]]:
    """:func:`_first_rows` compiled by numba."""
    from numba import njit

    return njit(cache=True, nogil=True)(_first_rows)


def _replay(vertices: _F64, c0: _I64, c1: _I64, q_init: _F64, border: npt.NDArray[np.bool_],
            prev0: _I64, prev1: _I64) -> _F64:
    """The position (K, 3) each collapse ``c1 -> c0`` gives ``c0``, in ``Simplify.h``'s own
    order of operations (``SymetricMatrix::det``, ``vertex_error``, ``std::min``): the two
    quadrics added, then their minimum, or on a singular quadric or a border edge the best of
    the two ends and their midpoint. ``prev0``/``prev1``: the collapse that last moved each end
    (-1: none, the vertex's own quadric and position). Compiled with numpy's error model, so a
    zero determinant gives infinities as in C++."""

    def det(q: _F64, a11: int, a12: int, a13: int, a21: int, a22: int, a23: int,
            a31: int, a32: int, a33: int) -> float:
        return float(q[a11] * q[a22] * q[a33] + q[a13] * q[a21] * q[a32] + q[a12] * q[a23] * q[a31]
                     - q[a13] * q[a22] * q[a31] - q[a11] * q[a23] * q[a32] - q[a12] * q[a21] * q[a33])

    def error(q: _F64, x: float, y: float, z: float) -> float:
        return float(q[0] * x * x + 2 * q[1] * x * y + 2 * q[2] * x * z + 2 * q[3] * x + q[4] * y * y
                     + 2 * q[5] * y * z + 2 * q[6] * y + q[7] * z * z + 2 * q[8] * z + q[9])

    K = len(c0)
    q_after = np.empty((K, 10))
    p_after = np.empty((K, 3))
    q = np.empty(10)
    e1p = np.empty(3)
    e2p = np.empty(3)
    e3p = np.empty(3)
    for k in range(K):
        a, b = prev0[k], prev1[k]
        for j in range(10):
            q[j] = (q_after[a, j] if a >= 0 else q_init[c0[k], j]) + (q_after[b, j] if b >= 0 else q_init[c1[k], j])
        for j in range(3):
            e1p[j] = p_after[a, j] if a >= 0 else vertices[c0[k], j]
            e2p[j] = p_after[b, j] if b >= 0 else vertices[c1[k], j]
        d = det(q, 0, 1, 2, 1, 4, 5, 2, 5, 7)
        p_after[k, 0] = -1 / d * det(q, 1, 2, 3, 4, 5, 6, 5, 7, 8)
        p_after[k, 1] = 1 / d * det(q, 0, 2, 3, 1, 5, 6, 2, 7, 8)
        p_after[k, 2] = -1 / d * det(q, 0, 1, 3, 1, 4, 6, 2, 5, 8)
        if d == 0 or (border[c0[k]] and border[c1[k]]):
            for j in range(3):
                e3p[j] = (e1p[j] + e2p[j]) / 2
            e1 = error(q, e1p[0], e1p[1], e1p[2])
            e2 = error(q, e2p[0], e2p[1], e2p[2])
            e3 = error(q, e3p[0], e3p[1], e3p[2])
            low = e3 if e3 < e2 else e2  # std::min(a, b) is (b < a) ? b : a
            low = low if low < e1 else e1
            for e, ep in ((e1, e1p), (e2, e2p), (e3, e3p)):  # the last equal to the least wins
                if e == low:
                    p_after[k, 0], p_after[k, 1], p_after[k, 2] = ep[0], ep[1], ep[2]
        q_after[k] = q
    return p_after


@functools.cache
def _compiled_replay() -> Callable[..., _F64]:
    """:func:`_replay` compiled by numba."""
    from numba import njit

    return njit(cache=True, nogil=True, error_model="numpy")(_replay)


@dataclass
class Progressive:
    """One simplification of a triangle mesh, cut at any face count.

    ``vertices`` (V, 3) float64 and ``faces`` (F, 3) as given to the simplifier (coincident
    vertices merged by the caller); :meth:`level` is the mesh a run of
    ``fast_simplification.simplify(vertices, faces, target_count=...)`` returns.
    """

    vertices: _F64
    faces: _I64
    collapses: _I64 = field(init=False, repr=False)
    _death: _I64 = field(init=False, repr=False)
    _sorted_death: _I64 = field(init=False, repr=False)
    _position: _F64 = field(init=False, repr=False)

    def __post_init__(self) -> None:
        import fast_simplification

        self.vertices = np.ascontiguousarray(self.vertices, np.float64)
        self.faces = np.ascontiguousarray(self.faces, np.int64)
        _, _, collapses = fast_simplification.simplify(self.vertices, self.faces, target_count=0,
                                                       return_collapses=True)
        self.collapses = np.asarray(collapses, np.int64).reshape(-1, 2)
        self._death = self._death_times()
        self._sorted_death = np.sort(self._death)
        self._position = self._positions()

    # -- which collapse removes each face -------------------------------------------------

    def _death_times(self) -> _I64:
        """Index of the collapse that removes each face (``K`` when none does): the first
        collapse after which two of its corners have one representative. Two vertices' chains
        of collapses are walked together in time order until they meet (compiled)."""
        K, n = len(self.collapses), len(self.vertices)
        when = np.full(n, K, np.int64)
        into = np.arange(n)
        when[self.collapses[:, 1]] = np.arange(K)
        into[self.collapses[:, 1]] = self.collapses[:, 0]
        return _compiled_death_times()(self.faces, when, into, K)

    def collapses_for(self, target_count: int) -> int:
        """How many collapses the simplifier makes for ``target_count`` faces: it stops after
        the first collapse that leaves at most that many (or when it can go no further)."""
        need = len(self.faces) - int(target_count)
        if need <= 0:
            return 0
        dying = int(np.searchsorted(self._sorted_death, len(self.collapses)))
        if need > dying:
            return len(self.collapses)
        return int(self._sorted_death[need - 1]) + 1

    # -- where each collapse puts its vertex ----------------------------------------------

    def _positions(self) -> _F64:
        """The position (K, 3) each collapse gives its surviving vertex."""
        c0, c1 = self.collapses[:, 0], self.collapses[:, 1]
        K = len(c0)
        q_init = _plane_quadrics(self.vertices, self.faces)
        border = _border(len(self.vertices), self.faces)
        # previous collapse into c0 (same group, earlier), last collapse into c1 before t
        order = np.lexsort((np.arange(K), c0))
        prev0 = np.full(K, -1, np.int64)
        same = c0[order[1:]] == c0[order[:-1]]
        prev0[order[1:][same]] = order[:-1][same]
        last_into = np.full(len(self.vertices), -1, np.int64)
        last_into[c0[order]] = order  # the group's last (largest t) wins
        prev1 = last_into[c1]
        # both come earlier than the collapse: one pass in collapse order has every input ready
        return _compiled_replay()(self.vertices, c0, c1, q_init, border, prev0, prev1)

    # -- a level ----------------------------------------------------------------------------

    def level(self, target_count: int) -> tuple[_F64, npt.NDArray[np.int32]]:
        """Vertices (n, 3) float64 and faces (m, 3) int32 of the simplifier's result for
        ``target_count`` faces."""
        k = self.collapses_for(target_count)
        c0, c1 = self.collapses[:k, 0], self.collapses[:k, 1]
        n = len(self.vertices)
        rep = np.arange(n)
        rep[c1] = c0
        while True:  # follow each vertex's collapses to its representative
            nxt = rep[rep]
            if np.array_equal(nxt, rep):
                break
            rep = nxt
        last = np.full(n, -1, np.int64)  # the last collapse into each vertex places it
        np.maximum.at(last, c0, np.arange(k))
        position = self.vertices.copy()
        moved = last >= 0
        position[moved] = self._position[last[moved]]
        faces = rep[self.faces[self._death >= k]]
        used = np.zeros(n, bool)
        used[faces.reshape(-1)] = True
        index = np.cumsum(used) - 1
        return position[used], index[faces].astype(np.int32)
