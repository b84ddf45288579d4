"""The files of a certificate the lab server approved on a PostgreSQL lab database: the signed
certificate, its DCC and its report (PDF, HTML), kept in the lab database itself, which is the record,
so that the bench that measured the run receives them on its next sync or export. Written by the
server's role alone, in the approval's one transaction.

Revision ID: 0012
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0012"
down_revision = "0011"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "certificate_files",
        sa.Column("certificate_id", sa.Text, nullable=False),
        sa.Column("run_uuid", sa.Text, nullable=False),
        sa.Column("name", sa.Text, nullable=False),
        sa.Column("sha256", sa.Text, nullable=False),
        sa.Column("content", sa.LargeBinary, nullable=False),
        sa.Column("stored_utc", sa.Text, nullable=False),
        sa.PrimaryKeyConstraint("certificate_id", "name"),
    )
    op.create_index("certificate_files_by_run", "certificate_files", ["run_uuid"])


def downgrade() -> None:
    op.drop_index("certificate_files_by_run", table_name="certificate_files")
    op.drop_table("certificate_files")
