"""offset_calibrations: the sensor offset baselines (issue 15), restored at start-up

Written by hand after ``service/store/models.py`` (``OffsetCalibrationRow``), in the style of ``0001``: the UTC
type decorator is written as its implementation type, so this script never imports application code.

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-24 02:00:00 UTC
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "offset_calibrations",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("t_from", sa.DateTime(timezone=True), nullable=False),
        sa.Column("t_to", sa.DateTime(timezone=True), nullable=False),
        sa.Column("source", sa.String(length=16), nullable=False),
        sa.Column("samples", sa.Integer(), nullable=False),
        sa.Column("offsets_c", sa.JSON(), nullable=False),
        sa.Column("sd_c", sa.JSON(), nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_offset_calibrations")),
    )
    op.create_index(op.f("ix_offset_calibrations_t_to"), "offset_calibrations", ["t_to"], unique=False)


def downgrade() -> None:
    op.drop_index(op.f("ix_offset_calibrations_t_to"), table_name="offset_calibrations")
    op.drop_table("offset_calibrations")
