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
    _run(engine, lambda cfg: alembic.command.upgrade(cfg, revision))


def downgrade(engine: Engine, revision: str) -> None:
    """Undo migrations down to ``revision`` (e.g. ``"0001_initial"``; ``"base"`` drops everything)."""
    _run(engine, lambda cfg: alembic.command.downgrade(cfg, revision))


def _run(engine: Engine, command) -> None:
    """Run an Alembic command on one connection in one transaction.

    On SQLite, ``batch_alter_table`` rebuilds a table (create a copy, copy the rows, drop, rename),
    and dropping a table that other rows reference fails while foreign keys are enforced; SQLite's
    own procedure for such changes (https://www.sqlite.org/lang_altertable.html, "other kinds of table
    schema changes") is: foreign keys off outside the transaction, change, ``PRAGMA foreign_key_check``
    before committing, foreign keys on again.
    """
    cfg = alembic_config()
    with engine.connect() as conn:
        sqlite = conn.dialect.name == "sqlite"
        if sqlite:
            conn.exec_driver_sql("PRAGMA foreign_keys=OFF")  # a no-op inside a transaction: before it
            conn.commit()
        try:
            with conn.begin():
                cfg.attributes["connection"] = conn
                command(cfg)
                if sqlite:
                    bad = conn.exec_driver_sql("PRAGMA foreign_key_check").fetchall()
                    if bad:
                        raise RuntimeError(f"migration left {len(bad)} rows with broken foreign keys, e.g. {bad[:3]}")
        finally:
            if sqlite:
                conn.exec_driver_sql("PRAGMA foreign_keys=ON")
                conn.commit()


def current_revision(engine: Engine) -> str | None:
    from alembic.runtime.migration import MigrationContext

    with engine.connect() as conn:
        return MigrationContext.configure(conn).get_current_revision()
