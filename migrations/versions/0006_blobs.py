"""A ``blobs`` table: large arrays that many map states share, stored once per database.

An ``sdr-htm`` map's snapshot holds its LSBH projection (6.3 MB of float32 at the default sizes), the same for
every map made with one seed and size; every map state and every archive of a merge held a copy (a merged
two-session ``cave3d`` database: 34.8 MB, 25 MB of it four copies of one projection). Map states and archives
written from this revision keep the projection's SHA-256 instead and the array is stored once here
(``mapserver.store.blobs``). States written before keep their copy and read as before.

Revision ID: 0006
Revises: 0005
Create Date: 2026-11-27
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0006"
down_revision = "0005"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "blobs",
        sa.Column("digest", sa.String(length=64), nullable=False),
        sa.Column("nbytes", sa.BigInteger(), nullable=False),
        sa.Column("data", sa.LargeBinary(), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint("digest"),
    )


def downgrade() -> None:
    op.drop_table("blobs")
