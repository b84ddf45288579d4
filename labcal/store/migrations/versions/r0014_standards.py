"""The lab's reference standards and the overrides approvers record for an overdue one.

``standards``: one row per reference standard (the DMM, the pitch and roll tables, a reference level),
found by its serial whatever its case (``serial_key``, unique), with its kind, model, manufacturer,
the number and issuer of its calibration certificate, when it was calibrated and when it is due
(ISO dates), the bench that uses it (``bench``: a station's name in the lab database; empty: none),
its status and notes.

``standard_overrides``: an approver's signed permission to run on an overdue standard: which standard
(``standard_key``), the due date it was overdue against (a recalibrated standard's new date ends it),
until which day it holds, the reason, the approver's name, role and key id, and the Ed25519 signature
over the rest. Appended, never changed.

``certificate_numbers``: the lab's own certificate numbers (the lab file's ``[laboratory]
certificate_number``), one per run (``run_uuid``, unique: a run's reissues and revisions keep its
number), counted without a gap within a ``scope`` (the year, or 0 for one sequence): ``seq`` is
unique in its scope.

Revision ID: 0014
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0014"
down_revision = "0013"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "standards",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("serial", sa.Text, nullable=False),
        sa.Column("serial_key", sa.Text, nullable=False, unique=True),
        sa.Column("kind", sa.Text, nullable=False),
        sa.Column("model", sa.Text, nullable=False, server_default=""),
        sa.Column("manufacturer", sa.Text, nullable=False, server_default=""),
        sa.Column("certificate", sa.Text, nullable=False),
        sa.Column("issued_by", sa.Text, nullable=False, server_default=""),
        sa.Column("calibrated_on", sa.Text, nullable=False),
        sa.Column("due_on", sa.Text, nullable=False),
        sa.Column("bench", sa.Text, nullable=False, server_default=""),
        sa.Column("status", sa.Text, nullable=False, server_default="active"),
        sa.Column("notes", sa.Text, nullable=False, server_default=""),
        sa.Column("created_utc", sa.Text, nullable=False),
        sa.Column("updated_utc", sa.Text, nullable=False),
    )
    op.create_table(
        "standard_overrides",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("standard_key", sa.Text, nullable=False),
        sa.Column("due_on", sa.Text, nullable=False),
        sa.Column("valid_until", sa.Text, nullable=False),
        sa.Column("reason", sa.Text, nullable=False),
        sa.Column("approver", sa.Text, nullable=False),
        sa.Column("role", sa.Text, nullable=False),
        sa.Column("key_id", sa.Text, nullable=False),
        sa.Column("signature", sa.Text, nullable=False),
        sa.Column("recorded_utc", sa.Text, nullable=False),
    )
    op.create_index("standard_overrides_by_standard", "standard_overrides", ["standard_key", "due_on"])
    op.create_table(
        "certificate_numbers",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("scope", sa.Integer, nullable=False),
        sa.Column("seq", sa.Integer, nullable=False),
        sa.Column("number", sa.Text, nullable=False, unique=True),
        sa.Column("run_uuid", sa.Text, nullable=False, unique=True),
        sa.Column("assigned_utc", sa.Text, nullable=False),
        sa.UniqueConstraint("scope", "seq", name="certificate_numbers_in_scope"),
    )


def downgrade() -> None:
    op.drop_table("certificate_numbers")
    op.drop_index("standard_overrides_by_standard", table_name="standard_overrides")
    op.drop_table("standard_overrides")
    op.drop_table("standards")
