"""Every revision of a run's certificate the lab server approves keeps its own files.

- ``certificate_files_by_run`` is no longer unique over (run_uuid, name): a run whose approved
  certificate is revised has one approved set per revision, each under its certificate id (the primary
  key, certificate_id and name, keeps each once, whichever approval or process stores it). The index
  stays, to find a run's files.

Revision ID: 0015
"""

from __future__ import annotations

from alembic import op

revision = "0015"
down_revision = "0014"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.drop_index("certificate_files_by_run", table_name="certificate_files")
    op.create_index("certificate_files_by_run", "certificate_files", ["run_uuid", "name"])


def downgrade() -> None:
    op.drop_index("certificate_files_by_run", table_name="certificate_files")
    op.create_index("certificate_files_by_run", "certificate_files", ["run_uuid", "name"], unique=True)
