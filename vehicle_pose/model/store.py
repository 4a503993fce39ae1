"""Prepared models on disk: a mesh's render arrays, levels of detail and exterior passes.

Parsing a CAD mesh, splitting its shading normals, decimating it to every level of detail and
finding its exterior faces costs seconds (a minute for millions of triangles), and each process
paid it again. A :class:`ModelStore` keeps the results in a folder, one entry per mesh keyed by
a hash of the mesh file's bytes, the texture folders, the preparation version and the versions
of the libraries whose output it holds, so that a prepared model loads in milliseconds and gives
the same arrays, hence the same poses, as one prepared in memory.

An entry is a ``manifest.json`` and content-addressed ``.npy`` arrays (named by the xxh3 hash of
their bytes, checked on every read). The files the mesh refers to (an OBJ's material library and
textures) are listed with their hashes and checked when the entry is opened; an entry whose
sources changed is rebuilt, and one that cannot be read or whose arrays do not match their names
is deleted and rebuilt: a cache entry is never trusted blindly. Entries grow as levels are
computed: what a registration computes that the entry lacks is added to it (under a file lock,
so concurrent processes only ever add).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import shutil
import threading
from collections.abc import Callable, Iterator, Sequence
from importlib import metadata as _metadata
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np
import numpy.typing as npt
import xxhash

from vehicle_pose.files import write_atomic
from vehicle_pose.model.mesh import Mesh, Part

if TYPE_CHECKING:
    from vehicle_pose.render.renderer import Renderer

__all__ = ["PREPARATION", "ModelStore", "Levels", "default_cache_dir", "default_budgets"]

log = logging.getLogger(__name__)

_T = TypeVar("_T")

PREPARATION = 1
"""Version of what an entry holds; raise it whenever preparation gives different arrays."""

_LIBRARIES = ("numpy", "trimesh", "fast-simplification")


def default_cache_dir() -> Path:
    """``$VEHICLE_POSE_CACHE_DIR``, else ``$XDG_CACHE_HOME/vehicle-pose``, else
    ``~/.cache/vehicle-pose`` (the XDG base directory convention)."""
    env = os.environ.get("VEHICLE_POSE_CACHE_DIR")
    if env:
        return Path(env)
    xdg = os.environ.get("XDG_CACHE_HOME")
    base = Path(xdg) if xdg and os.path.isabs(xdg) else Path.home() / ".cache"
    return base / "vehicle-pose"


def default_budgets(n_faces: int) -> list[int]:
    """The face budgets the registration's defaults ask levels of detail for: the view
    search's, the outline's and every level's (powers of two from ``min(4096, min_faces)``
    to the budget of a silhouette filling the largest working image), up to the mesh's size."""
    from vehicle_pose.registration.options import RegistrationOptions

    o = RegistrationOptions().pyramid
    low = min(4096, o.min_faces)
    high = max(o.min_faces, o.faces_per_pixel * o.max_size * o.max_size)
    out, b = [], low
    while True:
        out.append(b)
        if b >= n_faces or b >= high:
            return out
        b *= 2


def _versions() -> str:
    found = []
    for name in _LIBRARIES:
        try:
            found.append(f"{name}={_metadata.version(name)}")
        except _metadata.PackageNotFoundError:
            found.append(f"{name}=none")
    return ",".join(found)


def _file_hash(path: Path) -> str:
    h = xxhash.xxh3_128()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 22), b""):
            h.update(block)
    return h.hexdigest()


def _array_hash(a: npt.NDArray[Any]) -> str:
    h = xxhash.xxh3_128(f"{a.dtype.str}{a.shape}".encode())
    h.update(np.ascontiguousarray(a).data)
    return h.hexdigest()


class CorruptEntry(Exception):
    """An entry that cannot be read, or whose files do not match their hashes."""


_ARRAYS = ("vertices", "normals", "faces", "albedo", "uv", "texture")


class _Entry:
    """One prepared mesh's folder. Reads check every hash; writes are atomic (temporary file,
    then rename) and the manifest is merged under an exclusive lock."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self._arrays: dict[str, npt.NDArray[Any]] = {}
        self._meshes: dict[str, Mesh] = {}
        self._manifest: dict[str, Any] | None = None

    # -- files -------------------------------------------------------------------------------
    @contextlib.contextmanager
    def locked(self) -> Iterator[None]:
        self.folder.mkdir(parents=True, exist_ok=True)
        with (self.folder / ".lock").open("a") as f:
            fcntl.flock(f, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(f, fcntl.LOCK_UN)

    def manifest(self, *, reload: bool = False) -> dict[str, Any]:
        if self._manifest is None or reload:
            path = self.folder / "manifest.json"
            try:
                data = json.loads(path.read_text())
            except FileNotFoundError:
                data = {}
            except (OSError, ValueError) as exc:
                raise CorruptEntry(f"{path}: {exc}") from None
            if not isinstance(data, dict):
                raise CorruptEntry(f"{path}: not an object")
            self._manifest = data
        return self._manifest

    def _write_manifest(self, data: dict[str, Any]) -> None:
        write_atomic(self.folder / "manifest.json", (json.dumps(data, indent=1) + "\n").encode())
        self._manifest = data

    def update(self, change: Callable[[dict[str, Any]], None]) -> None:
        """Apply ``change`` to the manifest as it is on disk now, under the lock."""
        with self.locked():
            data = self.manifest(reload=True)
            change(data)
            self._write_manifest(data)

    def put_array(self, a: npt.NDArray[Any]) -> str:
        digest = _array_hash(a)
        path = self.folder / "arrays" / f"{digest}.npy"
        if not path.exists():
            import io

            buf = io.BytesIO()
            np.save(buf, np.ascontiguousarray(a), allow_pickle=False)
            write_atomic(path, buf.getvalue())
        self._arrays.setdefault(digest, a)
        return digest

    def get_array(self, digest: str) -> npt.NDArray[Any]:
        a = self._arrays.get(digest)
        if a is None:
            path = self.folder / "arrays" / f"{digest}.npy"
            try:
                a = np.load(path, allow_pickle=False)
            except (OSError, ValueError) as exc:
                raise CorruptEntry(f"{path}: {exc}") from None
            if _array_hash(a) != digest:
                raise CorruptEntry(f"{path}: contents do not match the name")
            self._arrays[digest] = a
        return a

    # -- meshes ------------------------------------------------------------------------------
    def put_mesh(self, mesh: Mesh) -> tuple[str, dict[str, Any]]:
        parts = []
        for p in mesh.parts:
            d: dict[str, Any] = {"name": p.name, "kind": p.kind, "one_sided": p.one_sided}
            for field in _ARRAYS:
                value = getattr(p, field)
                d[field] = None if value is None else self.put_array(value)
            parts.append(d)
        desc = {"source": mesh.source, "parts": parts}
        mesh_id = xxhash.xxh3_64_hexdigest(json.dumps(desc, sort_keys=True).encode())
        self._meshes.setdefault(mesh_id, mesh)
        return mesh_id, desc

    def get_mesh(self, mesh_id: str) -> Mesh:
        """The mesh of that id; the same object for the same id (one set of GPU buffers)."""
        mesh = self._meshes.get(mesh_id)
        if mesh is None:
            mesh = self._meshes[mesh_id] = self._read_mesh(mesh_id)
        return mesh

    def _read_mesh(self, mesh_id: str) -> Mesh:
        try:
            desc = self.manifest()["meshes"][mesh_id]
            parts = []
            for d in desc["parts"]:
                arrays = {f: None if d[f] is None else self.get_array(d[f]) for f in _ARRAYS}
                parts.append(Part(str(d["name"]), str(d["kind"]), one_sided=bool(d["one_sided"]), **arrays))  # type: ignore[arg-type]
            return Mesh(tuple(parts), source=str(desc["source"]))
        except CorruptEntry:
            raise
        except Exception as exc:  # a manifest that parses but does not describe meshes
            raise CorruptEntry(f"{self.folder}: mesh {mesh_id}: {type(exc).__name__}: {exc}") from None


class ModelStore:
    """A folder of prepared meshes (:func:`default_cache_dir` by default).

    Parameters
    ----------
    root : path, optional
    """

    def __init__(self, root: str | Path | None = None) -> None:
        self.root = Path(root) if root is not None else default_cache_dir() / "prepared"
        self._lock = threading.Lock()

    def __repr__(self) -> str:
        return f"ModelStore({str(self.root)!r})"

    def key(self, path: Path, texture_dirs: Sequence[Path]) -> str:
        """The entry name of a mesh file: a hash of its bytes, its suffix, the texture folders,
        :data:`PREPARATION` and the versions of the libraries that prepare it."""
        h = xxhash.xxh3_128()
        head = [f"preparation={PREPARATION}", path.suffix.lower(), _versions(), *map(str, texture_dirs)]
        h.update("\n".join(head).encode())
        h.update(_file_hash(path).encode())
        return h.hexdigest()

    def open(self, path: str | Path, texture_dirs: Sequence[str | Path] = ()) -> tuple[Mesh, Levels]:
        """The mesh of ``path`` with its levels, from the entry when a sound one exists; else
        loaded from the file and its entry started. Raises what :func:`load_mesh` raises."""
        p = Path(path).resolve()
        dirs = [Path(d).resolve() for d in texture_dirs]
        if not p.is_file():
            from vehicle_pose.errors import ModelError

            raise ModelError(f"mesh file {p} does not exist")
        entry = _Entry(self.root / self.key(p, dirs))
        try:
            manifest = entry.manifest()
            if manifest:
                if manifest.get("preparation") != PREPARATION or "full" not in manifest.get("lods", {}):
                    raise CorruptEntry("not a prepared model")
                if _sources_unchanged(manifest, p, dirs):
                    mesh = entry.get_mesh(manifest["lods"]["full"])
                    return mesh, Levels(mesh, entry)
                log.info("the files of prepared model %s changed; preparing it again", entry.folder)
                discard(entry)
        except CorruptEntry as exc:
            log.warning("prepared model %s is unreadable (%s); preparing it again", entry.folder, exc)
            discard(entry)
        entry = _Entry(entry.folder)
        from vehicle_pose.model.loading import load_mesh_recording

        mesh, read, missing = load_mesh_recording(p, texture_dirs=dirs)
        levels = Levels(mesh, entry)
        sources = [{"path": str(f), "hash": _file_hash(f)} for f in read if f.is_file()]
        try:
            mesh_id, desc = entry.put_mesh(mesh)

            def start(data: dict[str, Any]) -> None:
                data.clear()
                data.update(preparation=PREPARATION, mesh=str(p), sources=sources, missing=missing,
                            meshes={mesh_id: desc}, lods={"full": mesh_id}, exteriors={}, wheels={})

            entry.update(start)
        except OSError as exc:
            log.warning("cannot write prepared model %s: %s", entry.folder, exc)
            levels.entry = None
        return mesh, levels


def _get_mesh(entry: _Entry, mesh_id: Any) -> Mesh:
    return entry.get_mesh(mesh_id)


def _put_mesh(mesh: Mesh) -> Callable[[_Entry], tuple[Any, dict[str, Any]]]:
    """How :meth:`Levels._once` keeps a mesh: its arrays, its description under ``meshes``."""

    def write(entry: _Entry) -> tuple[Any, dict[str, Any]]:
        mesh_id, desc = entry.put_mesh(mesh)
        return mesh_id, {"meshes": {mesh_id: desc}}

    return write


def discard(entry: _Entry) -> None:
    shutil.rmtree(entry.folder, ignore_errors=True)


def _sources_unchanged(manifest: dict[str, Any], path: Path, dirs: Sequence[Path]) -> bool:
    for s in manifest.get("sources", []):
        f = Path(s["path"])
        if not f.is_file() or _file_hash(f) != s["hash"]:
            return False
    if manifest.get("missing"):
        from vehicle_pose.model.loading import resolves

        if any(resolves(path, dirs, name) for name in manifest["missing"]):
            return False
    return True


class Levels:
    """A mesh's levels of detail and exterior passes, each computed once and kept in memory
    and, with an entry, on disk (where a later process finds it)."""

    def __init__(self, mesh: Mesh, entry: _Entry | None = None) -> None:
        self.mesh = mesh
        self.entry = entry
        self._lods: dict[int, Mesh] = {}
        self._exteriors: dict[str, Mesh] = {}
        self._arrays: dict[tuple[str, str], dict[str, npt.NDArray[Any]]] = {}
        self._lock = threading.RLock()

    def _stored(self, section: str, key: str, read: Callable[[_Entry, Any], _T]) -> _T | None:
        """What the entry's ``section`` holds under ``key``, read by ``read(entry, reference)``;
        None where it holds nothing (an unreadable entry is discarded)."""
        if self.entry is None:
            return None
        try:
            ref = self.entry.manifest().get(section, {}).get(key)
            if ref is None:
                ref = self.entry.manifest(reload=True).get(section, {}).get(key)
            return None if ref is None else read(self.entry, ref)
        except CorruptEntry as exc:
            log.warning("prepared model %s is unreadable (%s); computing again", self.entry.folder, exc)
            discard(self.entry)
            self.entry = None
            return None

    def _store(self, section: str, key: str, write: Callable[[_Entry], tuple[Any, dict[str, Any]]]) -> None:
        """Keeps a value in the entry: ``write(entry)`` puts its files and returns the reference
        to keep under ``key`` in ``section`` and any other manifest sections to merge."""
        if self.entry is None:
            return
        entry = self.entry
        try:
            ref, more = write(entry)

            def add(data: dict[str, Any]) -> None:
                if data.get("preparation") != PREPARATION:
                    raise CorruptEntry("entry replaced meanwhile")
                for name, items in more.items():
                    data.setdefault(name, {}).update(items)
                data.setdefault(section, {})[key] = ref

            entry.update(add)
        except (OSError, CorruptEntry) as exc:
            log.warning("cannot add to prepared model %s: %s", entry.folder, exc)
            self.entry = None

    def _once(self, found: dict[Any, _T], key: Any, section: str, stored: str, make: Callable[[], _T],
              read: Callable[[_Entry, Any], _T],
              write: Callable[[_T], Callable[[_Entry], tuple[Any, dict[str, Any]]]]) -> _T:
        """``found[key]``: from memory, the entry's ``section`` under ``stored``, or ``make``.
        ``make`` runs outside the lock, so that one thread can make a level while another
        draws the exterior pass of the last; two threads making the same value get the same
        arrays, and the first is kept. ``read`` and ``write`` say how the value is kept in the
        entry (:func:`_get_mesh`, :func:`_put_mesh` for a mesh)."""
        with self._lock:
            value = found.get(key)
            if value is None:
                value = self._stored(section, stored, read)
                if value is not None:
                    found[key] = value
        if value is not None:
            return value
        value = make()
        with self._lock:
            if key not in found:
                self._store(section, stored, write(value))
                found[key] = value
            return found[key]

    def lod(self, max_faces: int, make: Callable[[int], Mesh]) -> Mesh:
        """The level for ``max_faces``: from memory, the entry, or ``make`` (:meth:`_once`)."""
        if self.mesh.n_faces <= max_faces:
            return self.mesh
        return self._once(self._lods, max_faces, "lods", str(max_faces), lambda: make(max_faces),
                          _get_mesh, _put_mesh)

    def _exterior_key(self, max_faces: int, renderer: Renderer) -> str:
        from vehicle_pose.render.exterior import exterior_faces

        gl = renderer.ctx.info.get("GL_RENDERER", "?")
        level = "full" if max_faces >= self.mesh.n_faces else str(max_faces)
        args = tuple((exterior_faces.__kwdefaults__ or {}).values())  # the pass's own settings
        return f"{level}|{gl}|{args}"

    def exterior(self, max_faces: int, mesh: Mesh, renderer: Renderer) -> Mesh:
        """The exterior pass of ``mesh`` (the level for ``max_faces``) on this renderer's GL
        implementation (its depth ties decide some faces, so it is part of the key); drawn
        outside the lock (:meth:`_once`)."""
        from vehicle_pose.render.exterior import exterior_faces

        key = self._exterior_key(max_faces, renderer)
        return self._once(self._exteriors, key, "exteriors", key, lambda: exterior_faces(renderer, mesh),
                          _get_mesh, _put_mesh)

    def missing(self, budgets: Sequence[int], renderer: Renderer) -> list[int]:
        """The budgets whose exterior pass is neither in memory nor in the entry."""
        keys = {b: self._exterior_key(b, renderer) for b in budgets}
        stored: dict[str, Any] = {}
        if self.entry is not None:
            try:
                stored = self.entry.manifest(reload=True).get("exteriors", {})
            except CorruptEntry:
                stored = {}
        return [b for b, k in keys.items() if k not in self._exteriors and k not in stored]

    def arrays(self, section: str, key: str, make: Callable[[], dict[str, npt.NDArray[Any]]]
               ) -> dict[str, npt.NDArray[Any]]:
        """Named arrays made once (``make``) and kept in memory and in the entry's ``section``
        under ``key`` (the view templates of :mod:`vehicle_pose.search.templates`;
        :meth:`_once`)."""

        def read(entry: _Entry, names: Any) -> dict[str, npt.NDArray[Any]]:
            if not isinstance(names, dict):
                raise CorruptEntry(f"{section} {key} is not a table of arrays")
            return {name: entry.get_array(digest) for name, digest in names.items()}

        def write(made: dict[str, npt.NDArray[Any]]) -> Callable[[_Entry], tuple[Any, dict[str, Any]]]:
            return lambda entry: ({name: entry.put_array(a) for name, a in made.items()}, {})

        return self._once(self._arrays, (section, key), section, key, make, read, write)

    def wheels(self, axes: str, make: Callable[[], dict[str, Any]]) -> dict[str, Any]:
        """Estimated wheel metadata for the axes and the estimate's version (``"up forward vN"``), kept
        with the entry."""
        if self.entry is not None:
            try:
                found = self.entry.manifest().get("wheels", {}).get(axes)
            except CorruptEntry:
                found = None
            if found is not None:
                return dict(found)
        value = make()
        if self.entry is not None:
            entry = self.entry
            try:
                entry.update(lambda data: data.setdefault("wheels", {}).__setitem__(axes, value))
            except (OSError, CorruptEntry) as exc:
                log.warning("cannot add to prepared model %s: %s", entry.folder, exc)
        return value
