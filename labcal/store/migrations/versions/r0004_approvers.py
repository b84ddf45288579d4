"""Approvers registered by the lab: name, role and Ed25519 public key of each person who
may approve a certificate. A name is active at most once; a key is registered once, ever.

Revision ID: 0004
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "approvers",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("name", sa.Text, nullable=False),
        sa.Column("role", sa.Text, nullable=False),
        sa.Column("public_key", sa.Text, nullable=False),
        sa.Column("key_id", sa.Text, nullable=False, unique=True),
        sa.Column("added_utc", sa.Text, nullable=False),
        sa.Column("revoked_utc", sa.Text),
    )
    op.create_index("approvers_active_name", "approvers", ["name"], unique=True,
                    sqlite_where=sa.text("revoked_utc IS NULL"),
                    postgresql_where=sa.text("revoked_utc IS NULL"))
