"""The calibration device's own history: each run's device-model estimate of the
misalignments a…k per calibration-device id, for `labcal device history`.

Revision ID: 0003
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "device_estimates",
        sa.Column("device_id", sa.Text, nullable=False),
        sa.Column("source", sa.Text, nullable=False),
        sa.Column("calibrated_utc", sa.Text, nullable=False),
        sa.Column("stored_utc", sa.Text, nullable=False),
        sa.Column("document", sa.Text, nullable=False),
        sa.PrimaryKeyConstraint("device_id", "source"),
    )
    op.create_index("device_estimates_by_date", "device_estimates", ["device_id", "calibrated_utc"])
