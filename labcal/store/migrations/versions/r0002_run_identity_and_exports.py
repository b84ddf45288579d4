"""Run identity and export hashes: a run gets a UUID (so a run folder whose database was restored or
re-created, ids reused, is recognised as another run's); run_exports keeps the SHA-256 of every file
labcal last wrote into a run folder. Existing runs get a UUID here.

Revision ID: 0002
"""

from __future__ import annotations

import uuid

import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column("runs", sa.Column("uuid", sa.Text))
    bind = op.get_bind()
    for (run_id,) in bind.execute(sa.text("SELECT id FROM runs")).fetchall():
        bind.execute(sa.text("UPDATE runs SET uuid=:u WHERE id=:i"), {"u": str(uuid.uuid4()), "i": run_id})
    op.create_index("runs_by_uuid", "runs", ["uuid"], unique=True)
    op.create_table(
        "run_exports",
        sa.Column("run_id", sa.Integer, sa.ForeignKey("runs.id"), nullable=False),
        sa.Column("name", sa.Text, nullable=False),
        sa.Column("sha256", sa.Text, nullable=False),
        sa.PrimaryKeyConstraint("run_id", "name"),
    )
