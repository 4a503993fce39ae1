"""Bring the database schema to the newest migration (Alembic), from code or the launcher."""

from __future__ import annotations

from pathlib import Path

from alembic import command
from alembic.config import Config

from core.config import get_settings

_SCRIPTS = Path(__file__).resolve().parent / "migrations"


def alembic_config(database_url: str | None = None) -> Config:
    """Alembic's configuration for this package's migrations and ``database_url``."""
    cfg = Config()
    cfg.set_main_option("script_location", str(_SCRIPTS))
    cfg.set_main_option("sqlalchemy.url", (database_url or get_settings().database_url).replace("%", "%%"))
    return cfg


def upgrade(database_url: str | None = None) -> None:
    """Apply every migration not yet applied."""
    command.upgrade(alembic_config(database_url), "head")
