"""Sessions gain ``activations``: per frame the active template (its stable identity) and whether it was new.

Issue 16: the report's activation timeline (OpenRatSLAM2 Fig. 6) needs every frame, not only the frames
that created experiences. NULL for sessions stored before this revision (the report then falls back to
one point per experience).

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-24
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0005"
down_revision = "0004"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("sessions") as batch:
        batch.add_column(sa.Column("activations", sa.LargeBinary(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("sessions") as batch:
        batch.drop_column("activations")
