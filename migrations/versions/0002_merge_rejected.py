"""Merge events gain the status ``rejected``: an online merge rolled back by its own verification (issue 12).

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-24
"""

from __future__ import annotations

from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("merge_events") as batch:
        batch.drop_constraint(op.f("ck_merge_events_status"), type_="check")
        batch.create_check_constraint("status", "status IN ('applied', 'undone', 'rejected')")


def downgrade() -> None:
    op.execute("DELETE FROM merge_events WHERE status = 'rejected'")
    with op.batch_alter_table("merge_events") as batch:
        batch.drop_constraint(op.f("ck_merge_events_status"), type_="check")
        batch.create_check_constraint("status", "status IN ('applied', 'undone')")
