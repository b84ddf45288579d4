"""The journal is tamper-evident, and each bench of a PostgreSQL lab is a role of its own.

Every record of a run carries ``digest``, the SHA-256 of its canonical form chained to the record
before it, and ``link``, its place in the run's chain (`labcal.store.chain`); the run's manifest
begins the chain (``runs.digest``, link 0). Records journaled before this revision keep NULL in
both: their runs are "journaled before digests", said so, never passed as intact. A link is unique
within its run, which also makes finding a run's last record one index lookup for the writer.

``station_roles`` maps a PostgreSQL role to the station it may append runs for (`labcal db
grant-station`); row-level security keys on it. A SQLite lab database has it too, empty (one schema).

Revision ID: 0008
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0008"
down_revision = "0007"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("runs") as batch:  # SQLite: plain ADD COLUMNs (no constraint)
        batch.add_column(sa.Column("digest", sa.Text))
    for table in ("points", "events"):
        with op.batch_alter_table(table) as batch:
            batch.add_column(sa.Column("link", sa.Integer))
            batch.add_column(sa.Column("digest", sa.Text))
        op.create_index(f"{table}_by_link", table, ["run_id", "link"], unique=True)
    op.create_table(
        "station_roles",
        sa.Column("role", sa.Text, primary_key=True),
        sa.Column("station", sa.Text, nullable=False),
    )
