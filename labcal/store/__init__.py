"""The store: everything labcal keeps, and the only code that speaks to a database.

The lab database's schema (`labcal.store.schema`, SQLAlchemy Core) and its Alembic history
(`labcal.store.migrations`, with ``head.sqlite.sql``, the dump of what the migrations make), the
database opened (`labcal.store.labdb`) and the bench roles' grants (`labcal.store.roles`); the run
journal, the events' first and durable record (`labcal.store.journal`), its chain of digests
(`labcal.store.chain`) and its sending to the lab's PostgreSQL (`labcal.store.sync`); the reads of
what the lab knows (`labcal.store.labquery`, `labcal.store.lab_certificates`,
`labcal.store.lab_points`, `labcal.store.instruments`); and a run's folder, whose files are exports of
the journal (`labcal.store.rundir`, `labcal.store.exports`, `labcal.store.record`, `labcal.store.lock`).

The run machinery (`labcal.run`), the documents and the application layer call it; only modules
here import sqlite3, SQLAlchemy, Alembic or psycopg (an import contract in ``pyproject.toml`` says
so, without exceptions). A caller names the handles it passes back (a connection, an engine) from
`labcal.store.handles`.
"""
