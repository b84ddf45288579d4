"""Every journaled record reaches the lab database exactly once: an event keeps the id
it has in its station's journal (``events.origin_id``, unique per run), so sending it again after
an outage adds nothing; and a station's journal keeps, per lab database it sends to, how far it has
sent (``sync_cursors``: the last points rowid, events id and certificates rowid sent) and which lab
run each of its runs is (``sync_runs``: by uuid, with the status last sent). Lab databases and
journals have one schema, so both tables exist in both (empty where unused).

Revision ID: 0007
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0007"
down_revision = "0006"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("events") as batch:  # SQLite: a plain ADD COLUMN (no constraint)
        batch.add_column(sa.Column("origin_id", sa.Integer))
    op.create_index("events_by_origin", "events", ["run_id", "origin_id"], unique=True)
    op.create_table(
        "sync_cursors",
        sa.Column("target", sa.Text, nullable=False),
        sa.Column("name", sa.Text, nullable=False),
        sa.Column("position", sa.Integer, nullable=False),
        sa.PrimaryKeyConstraint("target", "name"),
    )
    op.create_table(
        "sync_runs",
        sa.Column("target", sa.Text, nullable=False),
        sa.Column("run_id", sa.Integer, sa.ForeignKey("runs.id"), nullable=False),
        sa.Column("lab_run_id", sa.Integer, nullable=False),
        sa.Column("sent", sa.Text, nullable=False),
        sa.PrimaryKeyConstraint("target", "run_id"),
    )
