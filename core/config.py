"""The service's settings: one object, read from ``VP_``-prefixed environment variables."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Literal

from pydantic import Field, SecretStr, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    """Everything the API, the workers and the launcher are configured by.

    Defaults are the embedded development set-up: SQLite and files under ``data_dir``, a Redis
    on localhost. ``environment="production"`` refuses the unsafe ones.
    """

    model_config = SettingsConfigDict(env_prefix="VP_", env_file=".env", extra="ignore")

    environment: Literal["development", "production"] = "development"
    data_dir: Path = Path("data")
    database_url: str = ""
    broker_url: str = "redis://127.0.0.1:6379/0"
    storage_url: str = ""
    s3_endpoint_url: str | None = None
    s3_region: str = "us-east-1"
    s3_access_key: SecretStr | None = None
    s3_secret_key: SecretStr | None = None
    models_dir: Path | None = None
    upload_models_dir: Path | None = None
    prepared_dir: Path | None = None

    max_upload_bytes: int = Field(default=25 * 1024 * 1024, gt=0)
    max_photo_pixels: int = Field(default=50_000_000, gt=0)
    max_mesh_bytes: int = Field(default=200 * 1024 * 1024, gt=0)
    body_timeout_s: float = Field(default=60.0, gt=0.0)
    job_soft_time_limit_s: int = Field(default=240, gt=0)
    job_hard_time_limit_s: int = Field(default=300, gt=0)
    visibility_timeout_s: int = Field(default=600, gt=0)
    max_attempts: int = Field(default=3, ge=1)
    lease_s: float = Field(default=30.0, gt=0.0)
    heartbeat_interval_s: float = Field(default=5.0, gt=0.0)
    progress_interval_s: float = Field(default=0.5, ge=0.0)
    warm_timeout_s: float = Field(default=900.0, gt=0.0)
    broker_timeout_s: float = Field(default=3.0, gt=1.0)
    worker_max_memory_mb: int = Field(default=1500, gt=100)
    bootstrap_admin_key: SecretStr | None = None
    bootstrap_client_key: SecretStr | None = None

    @model_validator(mode="after")
    def _derived_and_safe(self) -> Settings:
        if not self.database_url:
            self.database_url = f"sqlite:///{(self.data_dir / 'vehicle_pose.db').resolve()}"
        if not self.storage_url:
            self.storage_url = str((self.data_dir / "storage").resolve())
        if self.upload_models_dir is None:
            self.upload_models_dir = (self.data_dir / "models").resolve()
        if self.prepared_dir is None:
            self.prepared_dir = (self.data_dir / "prepared").resolve()
        if self.job_soft_time_limit_s >= self.job_hard_time_limit_s:
            raise ValueError("job_soft_time_limit_s must be below job_hard_time_limit_s")
        if self.visibility_timeout_s <= self.job_hard_time_limit_s:
            raise ValueError("visibility_timeout_s must exceed job_hard_time_limit_s, "
                             "or running jobs are delivered twice")
        if not 2.0 * self.heartbeat_interval_s < self.lease_s < self.visibility_timeout_s:
            raise ValueError("lease_s must exceed twice heartbeat_interval_s (or a live job's lease runs out "
                             "between two heartbeats) and be below visibility_timeout_s")
        if self.environment == "production":
            if self.database_url.startswith("sqlite"):
                raise ValueError("production needs a server database (VP_DATABASE_URL), not SQLite")
            for name in ("bootstrap_admin_key", "bootstrap_client_key"):
                key = getattr(self, name)
                if key is not None and len(key.get_secret_value()) < 24:
                    raise ValueError(f"VP_{name.upper()} must be at least 24 characters in production")
        return self


@lru_cache
def get_settings() -> Settings:
    """The process's settings, read once."""
    return Settings()
