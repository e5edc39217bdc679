"""Alembic environment: uses the connection handed over in ``config.attributes['connection']``."""

from alembic import context

from hybridloc.server.db import Base

config = context.config
conn = config.attributes.get("connection")
if conn is None:
    raise RuntimeError("run migrations through hybridloc (hybridloc db upgrade), which passes a connection")
context.configure(connection=conn, target_metadata=Base.metadata, render_as_batch=conn.dialect.name == "sqlite", compare_type=True)
with context.begin_transaction():
    context.run_migrations()
