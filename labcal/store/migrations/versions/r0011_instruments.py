"""The lab's instrument register: one row per instrument the lab calibrates, found by its serial
whatever its case (``serial_key``, unique: the serial case-folded, so ``acc-0042`` can never become
a second instrument beside ``ACC-0042``), with its model, manufacturer, customer, owner, location,
calibration interval in days (none: not yet set), status (active, retired, out-for-repair) and notes.

Revision ID: 0011
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0011"
down_revision = "0010"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "instruments",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("serial", sa.Text, nullable=False),
        sa.Column("serial_key", sa.Text, nullable=False, unique=True),
        sa.Column("model", sa.Text, nullable=False, server_default=""),
        sa.Column("manufacturer", sa.Text, nullable=False, server_default=""),
        sa.Column("customer", sa.Text, nullable=False, server_default=""),
        sa.Column("owner", sa.Text, nullable=False, server_default=""),
        sa.Column("location", sa.Text, nullable=False, server_default=""),
        sa.Column("interval_days", sa.Integer),
        sa.Column("status", sa.Text, nullable=False, server_default="active"),
        sa.Column("notes", sa.Text, nullable=False, server_default=""),
        sa.Column("created_utc", sa.Text, nullable=False),
        sa.Column("updated_utc", sa.Text, nullable=False),
    )
