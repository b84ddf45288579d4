"""What a bench's journal audited reaches the lab's audit trail once, and a run's approved certificate
is kept once.

- ``audit.origin``: a row copied into the lab's audit trail from a bench's journal (an approver
  registered or revoked there) names the digest it had in that journal; unique, so a sync repeated
  or replayed after a kill appends it once. NULL for a row written where it happened.
- ``certificate_files_by_run`` becomes unique over (run_uuid, name): one approved file of each name
  per run, whichever approval (or process) stores it.

Revision ID: 0013
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0013"
down_revision = "0012"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("audit") as batch:  # SQLite: a plain ADD COLUMN
        batch.add_column(sa.Column("origin", sa.Text))
    op.create_index("audit_by_origin", "audit", ["origin"], unique=True)
    op.drop_index("certificate_files_by_run", table_name="certificate_files")
    op.create_index("certificate_files_by_run", "certificate_files", ["run_uuid", "name"], unique=True)


def downgrade() -> None:
    op.drop_index("certificate_files_by_run", table_name="certificate_files")
    op.create_index("certificate_files_by_run", "certificate_files", ["run_uuid"])
    op.drop_index("audit_by_origin", table_name="audit")
    with op.batch_alter_table("audit") as batch:
        batch.drop_column("origin")
