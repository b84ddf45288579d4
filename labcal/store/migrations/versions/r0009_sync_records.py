"""The lab's records other than runs reach the lab database exactly once, and again when they change:
a journal keeps, per lab database and per record (a certificate, a device estimate, an approver, a
settle pool), the state it last sent (``sync_sent``: its key, and the columns that change when the
record does: a certificate's digest, an estimate's storing time, an approver's revocation, a pool's
update time), and when it last had everything sent there (``sync_targets``), so that a bench that
cannot reach the lab says how old what it shows is.

Revision ID: 0009
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0009"
down_revision = "0008"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "sync_sent",
        sa.Column("target", sa.Text, nullable=False),
        sa.Column("name", sa.Text, nullable=False),
        sa.Column("key", sa.Text, nullable=False),
        sa.Column("state", sa.Text, nullable=False),
        sa.PrimaryKeyConstraint("target", "name", "key"),
    )
    op.create_table(
        "sync_targets",
        sa.Column("target", sa.Text, primary_key=True),
        sa.Column("synced_utc", sa.Text, nullable=False),
    )
