"""Job leases for distributed workers (issue 15): who runs a job and until when its lease holds.

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-24

``lease_owner`` names the worker running the job, ``lease_expires_at`` is pushed forward by its
heartbeat; a running job whose lease expired lost its worker and is taken over. The index on
(``map_name``, ``status``) serves the per-map claim of the Celery engine.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("jobs") as batch:
        batch.add_column(sa.Column("lease_owner", sa.String(length=200), nullable=True))
        batch.add_column(sa.Column("lease_expires_at", sa.DateTime(timezone=True), nullable=True))
    op.create_index("ix_jobs_map_name_status", "jobs", ["map_name", "status"])


def downgrade() -> None:
    op.drop_index("ix_jobs_map_name_status", table_name="jobs")
    with op.batch_alter_table("jobs") as batch:
        batch.drop_column("lease_expires_at")
        batch.drop_column("lease_owner")
