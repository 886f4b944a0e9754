"""Initial schema: maps, sessions, templates, pose-cell links, experiences, links, map states, evidence,
merge events and archives (issue 5), API tokens and jobs (issue 6).

Revision ID: 0001
Revises:
Create Date: 2026-11-23

Written from ``alembic revision --autogenerate`` against mapserver/store/models.py and reviewed by hand;
tests/mapserver/store/test_migrations.py checks that the models and this revision agree.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None


def _id() -> sa.types.TypeEngine:
    """BIGINT keys, INTEGER on SQLite (so that the column aliases the rowid)."""
    return sa.BigInteger().with_variant(sa.Integer(), "sqlite")


def _stamp(name: str, nullable: bool = False) -> sa.Column:
    return sa.Column(name, sa.DateTime(timezone=True), nullable=nullable)


def _double(name: str, nullable: bool = False) -> sa.Column:
    return sa.Column(name, sa.Double(), nullable=nullable)


def upgrade() -> None:
    op.create_table(
        "maps",
        sa.Column("id", _id(), nullable=False),
        sa.Column("name", sa.String(length=200), nullable=False),
        sa.Column("version", sa.BigInteger(), nullable=False),
        sa.Column("params", sa.JSON(), nullable=False),
        _stamp("created_at"),
        _stamp("updated_at"),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_maps")),
        sa.UniqueConstraint("name", name=op.f("uq_maps_name")),
        sqlite_autoincrement=True,
    )
    op.create_table(
        "sessions",
        sa.Column("id", _id(), nullable=False),
        sa.Column("name", sa.String(length=200), nullable=False),
        sa.Column("map_id", _id(), nullable=True),
        sa.Column("source", sa.String(length=40), nullable=False),
        sa.Column("log_name", sa.String(length=500), nullable=False),
        sa.Column("log_sha256", sa.String(length=64), nullable=False),
        sa.Column("topics", sa.JSON(), nullable=False),
        sa.Column("topics_key", sa.String(length=64), nullable=False),
        sa.Column("params", sa.JSON(), nullable=False),
        sa.Column("code_version", sa.String(length=64), nullable=False),
        sa.Column("status", sa.String(length=16), nullable=False),
        sa.Column("frames_processed", sa.BigInteger(), nullable=False),
        sa.Column("frames_total", sa.BigInteger(), nullable=True),
        _double("first_stamp", nullable=True),
        _double("last_stamp", nullable=True),
        sa.Column("reckoning", sa.LargeBinary(), nullable=True),
        sa.Column("reckoning_pose", sa.JSON(), nullable=True),
        _stamp("started_at"),
        _stamp("finished_at", nullable=True),
        _stamp("updated_at"),
        sa.CheckConstraint("status IN ('partial', 'complete')", name=op.f("ck_sessions_status")),
        sa.ForeignKeyConstraint(["map_id"], ["maps.id"], name=op.f("fk_sessions_map_id_maps"), ondelete="SET NULL"),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_sessions")),
        sa.UniqueConstraint("log_sha256", "topics_key", name=op.f("uq_sessions_log_sha256_topics_key")),
        sa.UniqueConstraint("name", name=op.f("uq_sessions_name")),
        sqlite_autoincrement=True,
    )
    op.create_index(op.f("ix_sessions_log_sha256"), "sessions", ["log_sha256"])
    op.create_index(op.f("ix_sessions_map_id"), "sessions", ["map_id"])

    op.create_table(
        "templates",
        sa.Column("session_id", _id(), nullable=False),
        sa.Column("origin_index", sa.BigInteger(), nullable=False),
        sa.Column("map_id", _id(), nullable=True),
        sa.Column("local_id", sa.BigInteger(), nullable=True),
        sa.Column("height", sa.Integer(), nullable=False),
        sa.Column("width", sa.Integer(), nullable=False),
        _double("mean"),
        sa.Column("data", sa.LargeBinary(), nullable=False),
        sa.ForeignKeyConstraint(["map_id"], ["maps.id"], name=op.f("fk_templates_map_id_maps"), ondelete="SET NULL"),
        sa.ForeignKeyConstraint(
            ["session_id"], ["sessions.id"], name=op.f("fk_templates_session_id_sessions"), ondelete="CASCADE"
        ),
        sa.PrimaryKeyConstraint("session_id", "origin_index", name=op.f("pk_templates")),
        sa.UniqueConstraint("map_id", "local_id", name=op.f("uq_templates_map_id_local_id")),
    )
    op.create_table(
        "pose_cell_links",
        sa.Column("map_id", _id(), nullable=False),
        sa.Column("seq", sa.BigInteger(), nullable=False),
        sa.Column("template", sa.BigInteger(), nullable=False),
        _double("pc_x"),
        _double("pc_y"),
        _double("pc_z", nullable=True),
        _double("pc_th"),
        _double("strength"),
        _double("decay"),
        sa.ForeignKeyConstraint(
            ["map_id", "template"],
            ["templates.map_id", "templates.local_id"],
            name=op.f("fk_pose_cell_links_map_id_template_templates"),
        ),
        sa.ForeignKeyConstraint(
            ["map_id"], ["maps.id"], name=op.f("fk_pose_cell_links_map_id_maps"), ondelete="CASCADE"
        ),
        sa.PrimaryKeyConstraint("map_id", "seq", name=op.f("pk_pose_cell_links")),
    )
    op.create_index("ix_pose_cell_links_map_id_template", "pose_cell_links", ["map_id", "template"])

    op.create_table(
        "experiences",
        sa.Column("map_id", _id(), nullable=False),
        sa.Column("local_id", sa.BigInteger(), nullable=False),
        sa.Column("session_id", _id(), nullable=False),
        sa.Column("origin_index", sa.BigInteger(), nullable=False),
        _double("x"),
        _double("y"),
        _double("z"),
        _double("qx"),
        _double("qy"),
        _double("qz"),
        _double("qw"),
        _double("yaw"),
        _double("pc_x"),
        _double("pc_y"),
        _double("pc_z", nullable=True),
        _double("pc_th"),
        sa.Column("template", sa.BigInteger(), nullable=False),
        _double("stamp"),
        sa.ForeignKeyConstraint(
            ["map_id", "template"],
            ["templates.map_id", "templates.local_id"],
            name=op.f("fk_experiences_map_id_template_templates"),
        ),
        sa.ForeignKeyConstraint(["map_id"], ["maps.id"], name=op.f("fk_experiences_map_id_maps"), ondelete="CASCADE"),
        sa.ForeignKeyConstraint(
            ["session_id"], ["sessions.id"], name=op.f("fk_experiences_session_id_sessions"), ondelete="CASCADE"
        ),
        sa.PrimaryKeyConstraint("map_id", "local_id", name=op.f("pk_experiences")),
        sa.UniqueConstraint("session_id", "origin_index", name=op.f("uq_experiences_session_id_origin_index")),
    )
    op.create_table(
        "links",
        sa.Column("map_id", _id(), nullable=False),
        sa.Column("seq", sa.BigInteger(), nullable=False),
        sa.Column("from_id", sa.BigInteger(), nullable=False),
        sa.Column("to_id", sa.BigInteger(), nullable=False),
        _double("dx"),
        _double("dy"),
        _double("dz"),
        _double("dyaw"),
        _double("dt"),
        _double("distance"),
        sa.Column("kind", sa.String(length=16), nullable=False),
        sa.CheckConstraint("kind IN ('odometry', 'loop', 'merge', 'manual')", name=op.f("ck_links_kind")),
        sa.ForeignKeyConstraint(
            ["map_id", "from_id"],
            ["experiences.map_id", "experiences.local_id"],
            name=op.f("fk_links_map_id_from_id_experiences"),
        ),
        sa.ForeignKeyConstraint(
            ["map_id", "to_id"],
            ["experiences.map_id", "experiences.local_id"],
            name=op.f("fk_links_map_id_to_id_experiences"),
        ),
        sa.ForeignKeyConstraint(["map_id"], ["maps.id"], name=op.f("fk_links_map_id_maps"), ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("map_id", "seq", name=op.f("pk_links")),
    )
    op.create_index("ix_links_map_id_from_id", "links", ["map_id", "from_id"])
    op.create_index("ix_links_map_id_to_id", "links", ["map_id", "to_id"])

    op.create_table(
        "map_states",
        sa.Column("map_id", _id(), nullable=False),
        sa.Column("lattice_rank", sa.SmallInteger(), nullable=False),
        sa.Column("frames", sa.BigInteger(), nullable=False),
        _double("last_stamp", nullable=True),
        sa.Column("current_template", sa.BigInteger(), nullable=False),
        sa.Column("current_experience", sa.BigInteger(), nullable=False),
        sa.Column("n_templates", sa.BigInteger(), nullable=False),
        sa.Column("n_experiences", sa.BigInteger(), nullable=False),
        sa.Column("n_links", sa.BigInteger(), nullable=False),
        sa.Column("n_pose_cell_links", sa.BigInteger(), nullable=False),
        sa.Column("pc_activity", sa.LargeBinary(), nullable=False),
        sa.Column("arrays", sa.LargeBinary(), nullable=False),
        sa.Column("manifest", sa.JSON(), nullable=False),
        _stamp("updated_at"),
        sa.ForeignKeyConstraint(["map_id"], ["maps.id"], name=op.f("fk_map_states_map_id_maps"), ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("map_id", name=op.f("pk_map_states")),
    )
    op.create_table(
        "evidence",
        sa.Column("session_id", _id(), nullable=False),
        sa.Column("origin_index", sa.BigInteger(), nullable=False),
        _double("frame_stamp"),
        _double("offset_s"),
        sa.Column("width", sa.Integer(), nullable=False),
        sa.Column("height", sa.Integer(), nullable=False),
        sa.Column("media_type", sa.String(length=40), nullable=False),
        sa.Column("data", sa.LargeBinary(), nullable=False),
        sa.ForeignKeyConstraint(
            ["session_id"], ["sessions.id"], name=op.f("fk_evidence_session_id_sessions"), ondelete="CASCADE"
        ),
        sa.PrimaryKeyConstraint("session_id", "origin_index", name=op.f("pk_evidence")),
    )

    # -- merge events and archived map states (issue 5)
    op.create_table(
        "merge_events",
        sa.Column("id", _id(), nullable=False),
        sa.Column("map_id", _id(), nullable=True),
        sa.Column("map_name", sa.String(length=200), nullable=False),
        sa.Column("mode", sa.String(length=16), nullable=False),
        sa.Column("status", sa.String(length=16), nullable=False),
        sa.Column("confirmations", sa.Integer(), nullable=False),
        sa.Column("lattice_offset", sa.JSON(), nullable=False),
        _double("tx"),
        _double("ty"),
        _double("tz"),
        _double("qx"),
        _double("qy"),
        _double("qz"),
        _double("qw"),
        _double("yaw"),
        sa.Column("matches", sa.JSON(), nullable=False),
        sa.Column("details", sa.JSON(), nullable=True),
        _stamp("created_at"),
        _stamp("undone_at", nullable=True),
        sa.CheckConstraint("status IN ('applied', 'undone')", name=op.f("ck_merge_events_status")),
        sa.ForeignKeyConstraint(
            ["map_id"], ["maps.id"], name=op.f("fk_merge_events_map_id_maps"), ondelete="SET NULL"
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_merge_events")),
        sqlite_autoincrement=True,
    )
    op.create_index("ix_merge_events_map_id_created_at", "merge_events", ["map_id", "created_at"])
    op.create_table(
        "merge_event_sessions",
        sa.Column("event_id", _id(), nullable=False),
        sa.Column("session_id", _id(), nullable=False),
        sa.Column("role", sa.String(length=16), nullable=False),
        sa.ForeignKeyConstraint(
            ["event_id"],
            ["merge_events.id"],
            name=op.f("fk_merge_event_sessions_event_id_merge_events"),
            ondelete="CASCADE",
        ),
        sa.ForeignKeyConstraint(
            ["session_id"],
            ["sessions.id"],
            name=op.f("fk_merge_event_sessions_session_id_sessions"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("event_id", "session_id", name=op.f("pk_merge_event_sessions")),
    )
    op.create_table(
        "map_archives",
        sa.Column("id", _id(), nullable=False),
        sa.Column("event_id", _id(), nullable=True),
        sa.Column("role", sa.String(length=16), nullable=True),
        sa.Column("map_id", _id(), nullable=True),
        sa.Column("map_name", sa.String(length=200), nullable=False),
        sa.Column("map_version", sa.BigInteger(), nullable=True),
        sa.Column("params", sa.JSON(), nullable=False),
        sa.Column("session_ids", sa.JSON(), nullable=False),
        sa.Column("n_templates", sa.BigInteger(), nullable=False),
        sa.Column("n_experiences", sa.BigInteger(), nullable=False),
        sa.Column("n_links", sa.BigInteger(), nullable=False),
        sa.Column("state", sa.LargeBinary(), nullable=False),
        _stamp("created_at"),
        sa.ForeignKeyConstraint(
            ["event_id"],
            ["merge_events.id"],
            name=op.f("fk_map_archives_event_id_merge_events"),
            ondelete="CASCADE",
        ),
        sa.ForeignKeyConstraint(
            ["map_id"], ["maps.id"], name=op.f("fk_map_archives_map_id_maps"), ondelete="SET NULL"
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_map_archives")),
        sqlite_autoincrement=True,
    )
    op.create_index(op.f("ix_map_archives_event_id"), "map_archives", ["event_id"])

    # -- REST API (issue 6)
    op.create_table(
        "api_tokens",
        sa.Column("id", _id(), nullable=False),
        sa.Column("token_sha256", sa.String(length=64), nullable=False),
        sa.Column("prefix", sa.String(length=16), nullable=False),
        sa.Column("scope", sa.String(length=8), nullable=False),
        sa.Column("label", sa.String(length=200), nullable=True),
        _stamp("created_at"),
        _stamp("last_used_at", nullable=True),
        _stamp("revoked_at", nullable=True),
        sa.CheckConstraint("scope IN ('read', 'write')", name=op.f("ck_api_tokens_scope")),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_api_tokens")),
        sa.UniqueConstraint("token_sha256", name=op.f("uq_api_tokens_token_sha256")),
        sqlite_autoincrement=True,
    )
    op.create_table(
        "jobs",
        sa.Column("id", _id(), nullable=False),
        sa.Column("status", sa.String(length=16), nullable=False),
        _double("progress"),
        sa.Column("error", sa.Text(), nullable=True),
        sa.Column("session_id", _id(), nullable=True),
        sa.Column("map_id", _id(), nullable=True),
        sa.Column("map_name", sa.String(length=200), nullable=True),
        sa.Column("upload_path", sa.String(length=1000), nullable=False),
        sa.Column("upload_name", sa.String(length=500), nullable=True),
        sa.Column("upload_sha256", sa.String(length=64), nullable=True),
        sa.Column("preset", sa.String(length=64), nullable=True),
        sa.Column("topics", sa.JSON(), nullable=True),
        sa.Column("options", sa.JSON(), nullable=True),
        _stamp("created_at"),
        _stamp("started_at", nullable=True),
        _stamp("finished_at", nullable=True),
        _stamp("updated_at"),
        sa.CheckConstraint("status IN ('queued', 'running', 'done', 'failed')", name=op.f("ck_jobs_status")),
        sa.CheckConstraint("progress >= 0 AND progress <= 1", name=op.f("ck_jobs_progress")),
        sa.ForeignKeyConstraint(["map_id"], ["maps.id"], name=op.f("fk_jobs_map_id_maps"), ondelete="SET NULL"),
        sa.ForeignKeyConstraint(
            ["session_id"], ["sessions.id"], name=op.f("fk_jobs_session_id_sessions"), ondelete="SET NULL"
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_jobs")),
        sqlite_autoincrement=True,
    )
    op.create_index("ix_jobs_status_created_at", "jobs", ["status", "created_at"])
    op.create_index(op.f("ix_jobs_upload_sha256"), "jobs", ["upload_sha256"])


def downgrade() -> None:
    op.drop_index(op.f("ix_jobs_upload_sha256"), table_name="jobs")
    op.drop_index("ix_jobs_status_created_at", table_name="jobs")
    op.drop_table("jobs")
    op.drop_table("api_tokens")
    op.drop_index(op.f("ix_map_archives_event_id"), table_name="map_archives")
    op.drop_table("map_archives")
    op.drop_table("merge_event_sessions")
    op.drop_index("ix_merge_events_map_id_created_at", table_name="merge_events")
    op.drop_table("merge_events")
    op.drop_table("evidence")
    op.drop_table("map_states")
    op.drop_index("ix_links_map_id_to_id", table_name="links")
    op.drop_index("ix_links_map_id_from_id", table_name="links")
    op.drop_table("links")
    op.drop_table("experiences")
    op.drop_index("ix_pose_cell_links_map_id_template", table_name="pose_cell_links")
    op.drop_table("pose_cell_links")
    op.drop_table("templates")
    op.drop_index(op.f("ix_sessions_map_id"), table_name="sessions")
    op.drop_index(op.f("ix_sessions_log_sha256"), table_name="sessions")
    op.drop_table("sessions")
    op.drop_table("maps")
