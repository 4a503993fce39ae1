"""The model library as the service sees it: shipped models, then models uploaded by admins."""

from __future__ import annotations

from functools import lru_cache

from vehicle_pose import ModelLibrary

from .config import get_settings


@lru_cache
def get_library() -> ModelLibrary:
    """The process's library; each model is loaded once per process and kept."""
    s = get_settings()
    return ModelLibrary(s.models_dir, extra_roots=[s.upload_models_dir] if s.upload_models_dir else [])
