"""Fencing tokens for job leases: ``jobs.lease_token``, a number that grows with every claim and takeover.

A job engine (embedded threads or a Celery worker) that claims a job gets the new value; every progress,
heartbeat and outcome write of that job is ``UPDATE ... WHERE id = ? AND lease_token = ?``, so a holder
that lost the job (its lease expired and another server took it over, or recovery queued it again) writes
nothing. Existing rows start at 0.

Revision ID: 0007
Revises: 0006
Create Date: 2026-12-01
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0007"
down_revision = "0006"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("jobs") as batch:
        batch.add_column(sa.Column("lease_token", sa.BigInteger(), nullable=False, server_default="0"))


def downgrade() -> None:
    with op.batch_alter_table("jobs") as batch:
        batch.drop_column("lease_token")
