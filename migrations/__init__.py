"""Alembic migrations of the hybridloc server database (installed as ``hybridloc.migrations``)."""
