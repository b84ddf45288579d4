"""Model settling's pooled step records: per instrument (or type) and station, the sums
`labcal.run.settle.TailPool` keeps, so that a run starts with the records of the runs before it.

Revision ID: 0005
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0005"
down_revision = "0004"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "settle_pools",
        sa.Column("pool_key", sa.Text, primary_key=True),
        sa.Column("identity", sa.Text, nullable=False),
        sa.Column("records", sa.Integer, nullable=False),
        sa.Column("sources", sa.Text, nullable=False),
        sa.Column("mismatch", sa.Text, nullable=False),
        sa.Column("sums", sa.LargeBinary, nullable=False),
        sa.Column("updated_utc", sa.Text, nullable=False),
    )
