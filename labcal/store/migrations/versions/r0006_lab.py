"""The lab as a whole: each run names its station and its number of points (the lab's
view shows "N / TOTAL" per station), and the lab server's users, with their password and API token
kept only as hashes.

Revision ID: 0006
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0006"
down_revision = "0005"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column("runs", sa.Column("station", sa.Text))
    op.add_column("runs", sa.Column("points_total", sa.Integer))
    op.create_table(
        "users",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("name", sa.Text, nullable=False, unique=True),
        sa.Column("role", sa.Text, nullable=False),
        sa.Column("password_hash", sa.Text, nullable=False),
        sa.Column("token_hash", sa.Text, nullable=False, unique=True),
        sa.Column("created_utc", sa.Text, nullable=False),
        sa.Column("disabled_utc", sa.Text),
    )
