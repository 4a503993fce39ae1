"""The model library as the service sees it: shipped models, then models uploaded by admins."""

from __future__ import annotations

from functools import lru_cache

from core.config import get_settings
from vehicle_pose import ModelLibrary, ModelStore


@lru_cache
def get_library() -> ModelLibrary:
    """The process's library; each model is loaded once per process and kept, and prepared
    once for every process in ``prepared_dir``."""
    s = get_settings()
    return ModelLibrary(s.models_dir, extra_roots=[s.upload_models_dir] if s.upload_models_dir else [],
                        store=get_store())


@lru_cache
def get_store() -> ModelStore:
    """Where the service keeps prepared models (``prepared_dir``, in the data directory)."""
    return ModelStore(get_settings().prepared_dir)
