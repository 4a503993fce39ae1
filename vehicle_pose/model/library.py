"""The model library: one folder per model holding ``model.json`` and its mesh.

Models are loaded once per process and kept (with their coarser levels of detail) in a small
cache, so a worker that registers many photos of the same model loads its mesh once; with a
:class:`~vehicle_pose.model.store.ModelStore`, what was prepared once is read back from disk by every
later process.
"""

from __future__ import annotations

import json
import re
import shutil
import threading
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from vehicle_pose.errors import ModelError, UnknownModelError
from vehicle_pose.model.metadata import UNITS, WHEEL_ESTIMATE, ModelInfo, WheelGeometry, estimate_wheels, parse_axis

if TYPE_CHECKING:
    from vehicle_pose.model.mesh import Mesh
    from vehicle_pose.model.parts import PartLabels
    from vehicle_pose.model.store import Levels, ModelStore
    from vehicle_pose.render.renderer import Renderer
    from vehicle_pose.search.templates import TemplateGrid, ViewTemplates

__all__ = ["AUTO", "VehicleModel", "ModelLibrary", "default_library_root", "install_model", "model_from_mesh"]


LOD_AGREEMENT = 0.98
"""Lowest outline IoU (256-pixel orthographic views) a level of detail must keep."""


def default_library_root() -> Path:
    """The ``vehicle_models/`` folder of this checkout."""
    return Path(__file__).resolve().parents[2] / "vehicle_models"


@dataclass(eq=False)
class VehicleModel:
    """A loaded model: metadata with complete wheel geometry, its mesh and its levels of detail."""

    info: ModelInfo
    mesh: Mesh
    levels: Levels | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if self.levels is None:
            from vehicle_pose.model.store import Levels

            self.levels = Levels(self.mesh)

    @property
    def wheels(self) -> WheelGeometry:
        assert self.info.wheels is not None
        return self.info.wheels

    def lod(self, max_faces: int) -> Mesh:
        """The coarsest mesh of about ``max_faces`` faces or more that keeps the model's outline.

        The mesh is decimated to ``max_faces``; when the decimation's outline differs from the
        full mesh's (IoU below :data:`LOD_AGREEMENT` along any of 14 directions, e.g. a CAD
        soup of thin shells that the simplifier tears), the budget is doubled until it holds,
        up to the full mesh. Levels are computed once per model (and kept in the model's store
        entry when it has one).
        """
        assert self.levels is not None
        return self.levels.lod(max_faces, self._decimate)

    def _decimate(self, max_faces: int) -> Mesh:
        mesh = self.mesh.decimated(max_faces)
        if self.mesh.outline_agreement(mesh) < LOD_AGREEMENT:
            mesh = self.lod(2 * max_faces)
        return mesh

    def exterior(self, max_faces: int, renderer: Renderer) -> Mesh:
        """The exterior pass (:func:`~vehicle_pose.render.exterior.exterior_faces`) of :meth:`lod`,
        computed once per model and GL driver."""
        assert self.levels is not None
        return self.levels.exterior(max_faces, self.lod(max_faces), renderer)

    def templates(self, renderer: Renderer, grid: TemplateGrid | None = None) -> ViewTemplates:
        """The model's edge templates over ``grid`` (:mod:`vehicle_pose.search.templates`), drawn
        once per model, axes and GL driver and kept with its prepared levels."""
        from vehicle_pose.search.templates import TemplateGrid, ViewTemplates

        assert self.levels is not None
        grid = grid if grid is not None else TemplateGrid()
        gl = renderer.ctx.info.get("GL_RENDERER", "?")
        key = f"{grid.key()}|{self.info.up} {self.info.forward}|{self.wheels.to_dict()}|{gl}"
        arrays = self.levels.arrays("templates", key, lambda: ViewTemplates.build(self, renderer, grid).arrays())
        return ViewTemplates.from_arrays(arrays)

    def part_labels(self) -> PartLabels:
        """Every face's part (:func:`~vehicle_pose.model.parts.label_faces`, with the model's part
        file where it has one), labelled once per model, axes, wheel metadata and part file and
        kept with its prepared levels."""
        import hashlib

        from vehicle_pose.model.parts import LABELLING, PartLabels, label_faces, read_part_file

        assert self.levels is not None
        path = self.info.parts_path
        listed = "none"
        if path is not None:
            try:
                listed = hashlib.sha256(path.read_bytes()).hexdigest()
            except OSError as exc:
                raise ModelError(f"cannot read part file {path}: {exc.strerror}") from None
        key = f"{LABELLING}|{self.info.up} {self.info.forward}|{self.wheels.to_dict()}|{listed}"

        def compute() -> dict[str, Any]:
            given = read_part_file(path, self.info.mesh_path) if path is not None else None
            return label_faces(self.mesh, self.info.up, self.wheels, given).arrays()

        return PartLabels.from_arrays(self.levels.arrays("parts", key, compute))

    def prepare(self, renderer: Renderer, budgets: Sequence[int] | None = None,
                progress: Callable[[str], None] | None = None) -> None:
        """Compute (or read back) every level the registration's defaults use and its exterior
        pass, so that no registration of this model prepares anything (``progress`` is told
        each step). The levels are made one after another on a thread (the simplifier keeps
        global state, so two decimations at once would corrupt each other), each while this
        thread draws the exterior pass of the one before: the pass's draws let go of Python's
        lock, the decimation's arrays and outlines mostly hold it."""
        import time
        from concurrent.futures import ThreadPoolExecutor

        from vehicle_pose.model.store import default_budgets

        todo = list(budgets if budgets is not None else default_budgets(self.mesh.n_faces))
        start = time.perf_counter()
        pool = ThreadPoolExecutor(1, thread_name_prefix="prepare-levels")
        try:
            levels = [pool.submit(self.lod, b) for b in todo]
            if any(b < self.mesh.n_faces for b in todo):
                _ = self.mesh.reference_outlines  # drawn here while the thread simplifies
            for b, level in zip(todo, levels, strict=True):
                level.result()
                mesh = self.exterior(b, renderer)
                if progress is not None:
                    progress(f"level {b}: {mesh.n_faces} faces ({time.perf_counter() - start:.1f} s in)")
            self.part_labels()
        finally:
            pool.shutdown(cancel_futures=True)  # after a failure, the levels not yet begun
        self.mesh.forget_simplification()  # every level is made: its record is dead weight


def _complete(info: ModelInfo, mesh: Mesh, levels: Levels | None = None) -> ModelInfo:
    """Fill in missing wheel metadata from the mesh and record that it was estimated."""
    if info.wheels is not None:
        return info

    def estimate() -> dict[str, object]:
        return estimate_wheels(mesh.vertices, parse_axis(info.up), parse_axis(info.forward),
                               [(p.vertices, p.faces) for p in mesh.parts]).to_dict()

    axes = f"{info.up} {info.forward} v{WHEEL_ESTIMATE}"
    found = levels.wheels(axes, estimate) if levels is not None else estimate()
    wheels = WheelGeometry.from_dict(found)
    return replace(info, wheels=wheels, estimated=tuple(sorted({*info.estimated, "wheels"})))


def _open(path: Path, texture_dirs: Sequence[Path], store: ModelStore | None) -> tuple[Mesh, Levels | None]:
    if store is None:
        from vehicle_pose.model.loading import load_mesh

        return load_mesh(path, texture_dirs=texture_dirs), None
    return store.open(path, texture_dirs)


def model_from_mesh(
    path: str | Path,
    *,
    up: str = "+z",
    forward: str = "+x",
    units: str = "m",
    meters_per_unit: float = 1.0,
    texture_dirs: tuple[str | Path, ...] = (),
    store: ModelStore | None = None,
) -> VehicleModel:
    """A model straight from a mesh file; its wheel metadata is estimated. With a ``store``,
    the mesh is read from its prepared entry when there is a sound one, and prepared into it
    otherwise."""
    p = Path(path).resolve()
    parse_axis(up), parse_axis(forward)
    if abs(parse_axis(up) @ parse_axis(forward)) > 0.5:
        raise ModelError(f"up {up} and forward {forward} must be different axes")
    dirs = tuple(Path(d) for d in texture_dirs)
    info = ModelInfo(p.stem, p.stem, p, units, meters_per_unit, up, forward, None, texture_dirs=dirs)
    mesh, levels = _open(p, dirs, store)
    return VehicleModel(_complete(info, mesh, levels), mesh, levels)


AUTO = "auto"
"""The model spec that asks for identification among every model of the library."""

MODEL_ID = re.compile(r"^[a-z0-9][a-z0-9_-]{0,63}$")
"""Model ids: lower-case letters, digits, ``-`` and ``_``, at most 64 characters."""


def install_model(
    root: str | Path,
    model_id: str,
    mesh_file: str | Path,
    *,
    name: str | None = None,
    up: str = "+z",
    forward: str = "+x",
    units: str = "m",
    store: ModelStore | None = None,
) -> ModelInfo:
    """Copy a mesh into ``root/model_id/`` with a ``model.json`` whose wheels are estimated
    (and, with a ``store``, its parsed mesh kept there for the workers).

    The mesh is loaded first, so a file that is not a usable mesh (no faces, unknown format,
    same up and forward axes) raises ModelError and leaves nothing behind. The metadata is
    written last, so a half-copied model is never listed.
    """
    if not MODEL_ID.match(model_id) or model_id == AUTO:
        raise ModelError(f"model id {model_id!r} must match {MODEL_ID.pattern} and not be {AUTO!r}")
    if units not in UNITS:
        raise ModelError(f"unknown units {units!r}; choose one of {', '.join(UNITS)}")
    src = Path(mesh_file)
    model = model_from_mesh(src, up=up, forward=forward, units=units, meters_per_unit=UNITS[units], store=store)
    folder = Path(root) / model_id
    if (folder / "model.json").exists():
        raise ModelError(f"model {model_id!r} exists already")
    folder.mkdir(parents=True, exist_ok=True)
    mesh_name = "model" + src.suffix.lower()
    shutil.copyfile(src, folder / mesh_name)
    info = replace(model.info, id=model_id, name=name or model_id, mesh_path=(folder / mesh_name).resolve())
    data = info.to_dict() | {"mesh": mesh_name, "source": "uploaded"}
    tmp = folder / "model.json.tmp"
    tmp.write_text(json.dumps(data, indent=2) + "\n")
    tmp.replace(folder / "model.json")
    return info


class ModelLibrary:
    """Models found under ``root`` (default: :func:`default_library_root`) and ``extra_roots``.

    Parameters
    ----------
    root : path, optional
    extra_roots : sequence of paths, keyword-only
        Further folders searched after ``root`` (for example models uploaded to a service);
        a model id found in an earlier folder hides the same id in a later one.
    cache_size : int, keyword-only
        How many loaded models to keep in memory.
    store : ModelStore, keyword-only, optional
        Where prepared models are kept between processes (none: every process prepares the
        models it loads).
    """

    def __init__(
        self,
        root: str | Path | None = None,
        *,
        extra_roots: Sequence[str | Path] = (),
        cache_size: int = 8,
        store: ModelStore | None = None,
    ) -> None:
        self.root = Path(root) if root is not None else default_library_root()
        self.roots = (self.root, *(Path(r) for r in extra_roots))
        self._cache: OrderedDict[str, VehicleModel] = OrderedDict()
        self._lock = threading.Lock()
        self._cache_size = cache_size
        self.store = store

    def ids(self) -> list[str]:
        """Ids of every model in the library, sorted."""
        found = {p.parent.name for r in self.roots if r.is_dir() for p in r.glob("*/model.json")}
        return sorted(found)

    def __contains__(self, model_id: object) -> bool:
        return isinstance(model_id, str) and self._metadata_path(model_id) is not None

    def _metadata_path(self, model_id: str) -> Path | None:
        if not model_id or "/" in model_id or "\\" in model_id or model_id.startswith("."):
            return None
        for r in self.roots:
            path = r / model_id / "model.json"
            if path.is_file():
                return path
        return None

    def info(self, model_id: str) -> ModelInfo:
        """Metadata of one model; UnknownModelError if there is none with this id."""
        path = self._metadata_path(model_id)
        if path is None:
            known = ", ".join(self.ids()) or "none"
            raise UnknownModelError(f"unknown model {model_id!r} (known: {known})")
        return ModelInfo.from_json(path)

    def resolve(self, spec: str, *, limit: int = 16) -> list[str]:
        """Model ids named by ``spec``: one id, ``a,b,c`` (candidates to identify among), or
        ``auto`` (every model of the library). UnknownModelError names any unknown id."""
        if spec.strip() == AUTO:
            ids = self.ids()
        else:
            ids = list(dict.fromkeys(p.strip() for p in spec.split(",") if p.strip()))
        if not ids:
            raise UnknownModelError(f"no model named in {spec!r}")
        if len(ids) > limit:
            raise UnknownModelError(f"{len(ids)} candidate models; at most {limit} may be identified at once")
        unknown = [i for i in ids if i not in self]
        if unknown:
            known = ", ".join(self.ids()) or "none"
            raise UnknownModelError(f"unknown model {', '.join(map(repr, unknown))} (known: {known})")
        return ids

    def forget(self, model_id: str) -> None:
        """Drop a cached model (after its files changed)."""
        with self._lock:
            self._cache.pop(model_id, None)

    def load(self, model_id: str) -> VehicleModel:
        """The loaded model, from the cache when it was loaded before."""
        with self._lock:
            cached = self._cache.get(model_id)
            if cached is not None:
                self._cache.move_to_end(model_id)
                return cached
        info = self.info(model_id)
        mesh, levels = _open(info.mesh_path, info.texture_dirs, self.store)
        model = VehicleModel(_complete(info, mesh, levels), mesh, levels)
        with self._lock:
            self._cache[model_id] = model
            while len(self._cache) > self._cache_size:
                self._cache.popitem(last=False)
        return model
