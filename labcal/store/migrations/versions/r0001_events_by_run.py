"""Index events by run: `Journal.events(run)` read the whole lab's events table for every run.

Revision ID: 0001
"""

from __future__ import annotations

from alembic import op

revision = "0001"
down_revision = "0000"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_index("events_by_run", "events", ["run_id", "id"])
