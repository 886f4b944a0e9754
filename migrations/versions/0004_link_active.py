"""Links gain ``active`` (false when robust relaxation switched the link off) and map states ``health``.

Issue 12 part 4: ``map_states.health`` holds the map's health figure computed when its state is
written (``{"residual", "switched_off", "links"}``; NULL for states written before this revision).

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-24
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("links") as batch:
        batch.add_column(sa.Column("active", sa.Boolean(), server_default=sa.true(), nullable=False))
    with op.batch_alter_table("map_states") as batch:
        batch.add_column(sa.Column("health", sa.JSON(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("map_states") as batch:
        batch.drop_column("health")
    with op.batch_alter_table("links") as batch:
        batch.drop_column("active")
