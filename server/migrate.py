"""Alembic migrations applied programmatically (``hybridloc db upgrade`` and at server start)."""

from __future__ import annotations

from pathlib import Path

import alembic.command
import alembic.config
from sqlalchemy.engine import Engine


def migrations_dir() -> Path:
    import hybridloc.migrations as m

    return Path(m.__file__).resolve().parent


def alembic_config(engine: Engine | None = None) -> alembic.config.Config:
    cfg = alembic.config.Config()
    cfg.set_main_option("script_location", str(migrations_dir()))
    return cfg


def upgrade(engine: Engine, revision: str = "head") -> None:
    cfg = alembic_config()
    with engine.begin() as conn:
        cfg.attributes["connection"] = conn
        alembic.command.upgrade(cfg, revision)


def current_revision(engine: Engine) -> str | None:
    from alembic.runtime.migration import MigrationContext

    with engine.connect() as conn:
        return MigrationContext.configure(conn).get_current_revision()
