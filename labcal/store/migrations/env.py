"""Alembic's environment: always called by labcal with an open connection (`labcal.store.labdb.upgrade`),
never from an alembic.ini, so that the lab database's location is labcal's to resolve."""

from __future__ import annotations

from alembic import context

from labcal.store.schema import METADATA

connection = context.config.attributes["connection"]
context.configure(connection=connection, target_metadata=METADATA, transaction_per_migration=False)
with context.begin_transaction():
    context.run_migrations()
