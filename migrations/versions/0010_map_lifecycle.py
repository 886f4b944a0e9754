"""Maps gain ``archived_at``: a deleted map is archived first and can be restored.

NULL (every map stored before this revision, and every live map) is a live map. A map with a time here is
archived: hidden from the listings, lookups and merge candidates, its content, sessions and merge events
kept as they are, its name still held; ``mapserver maps restore`` / ``POST /v1/maps/{name}/restore`` clear
it, ``--purge`` / ``DELETE ...?purge=true`` delete the map for good.

Revision ID: 0010
Revises: 0009
Create Date: 2026-12-06
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0010"
down_revision = "0009"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("maps") as batch:
        batch.add_column(sa.Column("archived_at", sa.DateTime(timezone=True), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("maps") as batch:
        batch.drop_column("archived_at")
