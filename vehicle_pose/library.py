"""The model library: one folder per model holding ``model.json`` and its mesh.

Models are loaded once per process and kept (with their coarser levels of detail) in a small
cache, so a worker that registers many photos of the same model loads its mesh once.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass, field, replace
from pathlib import Path

from .errors import ModelError, UnknownModelError
from .mesh import Mesh, load_mesh
from .metadata import ModelInfo, WheelGeometry, estimate_wheels, parse_axis

__all__ = ["VehicleModel", "ModelLibrary", "default_library_root", "model_from_mesh"]


def default_library_root() -> Path:
    """The ``vehicle_models/`` folder of this checkout."""
    return Path(__file__).resolve().parents[1] / "vehicle_models"


@dataclass(eq=False)
class VehicleModel:
    """A loaded model: metadata with complete wheel geometry, and its mesh."""

    info: ModelInfo
    mesh: Mesh
    _lods: dict[int, Mesh] = field(default_factory=dict, repr=False)

    @property
    def wheels(self) -> WheelGeometry:
        assert self.info.wheels is not None
        return self.info.wheels

    def lod(self, max_faces: int) -> Mesh:
        """The mesh decimated to about ``max_faces`` faces (the mesh itself when smaller)."""
        if self.mesh.n_faces <= max_faces:
            return self.mesh
        if max_faces not in self._lods:
            self._lods[max_faces] = self.mesh.decimated(max_faces)
        return self._lods[max_faces]


def _complete(info: ModelInfo, mesh: Mesh) -> ModelInfo:
    """Fill in missing wheel metadata from the mesh and record that it was estimated."""
    if info.wheels is not None:
        return info
    wheels = estimate_wheels(mesh.vertices, parse_axis(info.up), parse_axis(info.forward))
    return replace(info, wheels=wheels, estimated=tuple(sorted({*info.estimated, "wheels"})))


def model_from_mesh(
    path: str | Path,
    *,
    up: str = "+z",
    forward: str = "+x",
    units: str = "m",
    meters_per_unit: float = 1.0,
    texture_dirs: tuple[str | Path, ...] = (),
) -> VehicleModel:
    """A model straight from a mesh file; its wheel metadata is estimated."""
    p = Path(path).resolve()
    parse_axis(up), parse_axis(forward)
    if abs(parse_axis(up) @ parse_axis(forward)) > 0.5:
        raise ModelError(f"up {up} and forward {forward} must be different axes")
    dirs = tuple(Path(d) for d in texture_dirs)
    info = ModelInfo(p.stem, p.stem, p, units, meters_per_unit, up, forward, None, texture_dirs=dirs)
    mesh = load_mesh(p, texture_dirs=dirs)
    return VehicleModel(_complete(info, mesh), mesh)


class ModelLibrary:
    """Models found under ``root`` (default: :func:`default_library_root`).

    Parameters
    ----------
    root : path, optional
    cache_size : int, keyword-only
        How many loaded models to keep in memory.
    """

    def __init__(self, root: str | Path | None = None, *, cache_size: int = 8) -> None:
        self.root = Path(root) if root is not None else default_library_root()
        self._cache: OrderedDict[str, VehicleModel] = OrderedDict()
        self._lock = threading.Lock()
        self._cache_size = cache_size

    def ids(self) -> list[str]:
        """Ids of every model in the library, sorted."""
        if not self.root.is_dir():
            return []
        return sorted(p.parent.name for p in self.root.glob("*/model.json"))

    def info(self, model_id: str) -> ModelInfo:
        """Metadata of one model; UnknownModelError if there is none with this id."""
        path = self.root / model_id / "model.json"
        if "/" in model_id or "\\" in model_id or model_id.startswith(".") or not path.is_file():
            known = ", ".join(self.ids()) or "none"
            raise UnknownModelError(f"unknown model {model_id!r} (known: {known})")
        return ModelInfo.from_json(path)

    def load(self, model_id: str) -> VehicleModel:
        """The loaded model, from the cache when it was loaded before."""
        with self._lock:
            cached = self._cache.get(model_id)
            if cached is not None:
                self._cache.move_to_end(model_id)
                return cached
        info = self.info(model_id)
        mesh = load_mesh(info.mesh_path, texture_dirs=info.texture_dirs)
        model = VehicleModel(_complete(info, mesh), mesh)
        with self._lock:
            self._cache[model_id] = model
            while len(self._cache) > self._cache_size:
                self._cache.popitem(last=False)
        return model
