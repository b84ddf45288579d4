"""The lab server's audit trail: who signed in, who failed, who was locked out and by whom let back
in, every refusal (401/403), every approval and every change to the users and the approvers — when,
by whom, from where. Each row carries the SHA-256 of its content and of the previous row's digest,
and names that digest (``prev``, unique): an edited, removed or inserted row breaks the chain at that
point, and two writers cannot both append after the same row. And each user's API token keeps the
time it was issued (``token_utc``; NULL: when the user was added), so that a token can expire.

Revision ID: 0010
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0010"
down_revision = "0009"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "audit",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("utc", sa.Text, nullable=False),
        sa.Column("kind", sa.Text, nullable=False),
        sa.Column("account", sa.Text),
        sa.Column("actor", sa.Text),
        sa.Column("client", sa.Text),
        sa.Column("detail", sa.Text),
        sa.Column("prev", sa.Text, nullable=False, unique=True),
        sa.Column("digest", sa.Text, nullable=False),
    )
    op.create_index("audit_by_account", "audit", ["account", "id"])
    with op.batch_alter_table("users") as batch:  # SQLite: a plain ADD COLUMN
        batch.add_column(sa.Column("token_utc", sa.Text))

