"""The schema labcal created before it was versioned (journal.py and history.py, a8863ee): the
journal's runs, points and events, and the certificates issued.

Revision ID: 0000
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0000"
down_revision = None
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "runs",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("run_dir", sa.Text, nullable=False),
        sa.Column("plan_name", sa.Text, nullable=False),
        sa.Column("plan_text", sa.Text, nullable=False),
        sa.Column("plan_hash", sa.Text, nullable=False),
        sa.Column("station_text", sa.Text, nullable=False),
        sa.Column("station_hash", sa.Text, nullable=False),
        sa.Column("software_version", sa.Text, nullable=False),
        sa.Column("instrument_serial", sa.Text),
        sa.Column("device_id", sa.Text),
        sa.Column("operator", sa.Text),
        sa.Column("settings", sa.Text, nullable=False),
        sa.Column("metadata", sa.Text, nullable=False),
        sa.Column("started_utc", sa.Text, nullable=False),
        sa.Column("status", sa.Text, nullable=False),
        sa.Column("reason", sa.Text),
        sa.Column("ended_utc", sa.Text),
    )
    op.create_table(
        "points",
        sa.Column("run_id", sa.Integer, sa.ForeignKey("runs.id"), nullable=False),
        sa.Column("seq", sa.Integer, nullable=False),
        sa.Column("replicate", sa.Integer, nullable=False),
        sa.Column("y_deg", sa.Float, nullable=False),
        sa.Column("u_deg", sa.Float, nullable=False),
        sa.Column("pitch_deg", sa.Float, nullable=False),
        sa.Column("roll_deg", sa.Float, nullable=False),
        sa.Column("pitch_read", sa.Float),
        sa.Column("roll_read", sa.Float),
        sa.Column("attempt", sa.Integer, nullable=False),
        sa.Column("status", sa.Text, nullable=False),
        sa.Column("t_start", sa.Float),
        sa.Column("t_end", sa.Float),
        sa.Column("utc", sa.Text, nullable=False),
        sa.Column("n_samples", sa.Integer, nullable=False),
        sa.Column("vx", sa.Float), sa.Column("vy", sa.Float), sa.Column("vz", sa.Float),
        sa.Column("sd_vx", sa.Float), sa.Column("sd_vy", sa.Float), sa.Column("sd_vz", sa.Float),
        sa.Column("temp_c", sa.Float),
        sa.Column("settle_s", sa.Float),
        sa.Column("settle_verdict", sa.Text),
        sa.Column("samples", sa.LargeBinary),
        sa.PrimaryKeyConstraint("run_id", "seq"),
    )
    op.create_table(
        "events",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("run_id", sa.Integer, sa.ForeignKey("runs.id"), nullable=False),
        sa.Column("utc", sa.Text, nullable=False),
        sa.Column("station_time", sa.Float),
        sa.Column("kind", sa.Text, nullable=False),
        sa.Column("message", sa.Text, nullable=False),
        sa.Column("data", sa.Text),
    )
    op.create_table(
        "certificates",
        sa.Column("certificate_id", sa.Text, primary_key=True),
        sa.Column("serial", sa.Text, nullable=False),
        sa.Column("calibrated_utc", sa.Text, nullable=False),
        sa.Column("issued_utc", sa.Text, nullable=False),
        sa.Column("sha256", sa.Text, nullable=False),
        sa.Column("document", sa.Text, nullable=False),
    )
    op.create_index("certificates_by_serial", "certificates", ["serial", "calibrated_utc"])
