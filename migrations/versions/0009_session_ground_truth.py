"""Sessions gain ``ground_truth``: the log's ground-truth poses, decimated, for the viewer's overlay and APE.

Rows ``[stamp, x, y, z, qx, qy, qz, qw]`` (float64 LE, N × 8), kept by ``process`` when the log has a
ground-truth topic, or given later (``mapserver ground-truth``, ``PUT /v1/sessions/{name}/ground-truth``).
NULL for sessions stored before this revision and for logs without ground truth.

Revision ID: 0009
Revises: 0008
Create Date: 2026-12-06
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0009"
down_revision = "0008"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("sessions") as batch:
        batch.add_column(sa.Column("ground_truth", sa.LargeBinary(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("sessions") as batch:
        batch.drop_column("ground_truth")
