"""mechanics_calibrations: the commissioning of the growth's mechanics (issue 27), restored at start-up

Written by hand after ``service/store/models.py`` (``MechanicsCalibrationRow``), in the style of ``0002``: the
UTC type decorator is written as its implementation type, so this script never imports application code.

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-27 20:10:00 UTC
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0005"
down_revision = "0004"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "mechanics_calibrations",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("set_by", sa.String(length=64), nullable=False),
        sa.Column("source", sa.String(length=16), nullable=False),
        sa.Column("restraint", sa.Double(), nullable=False),
        sa.Column("alpha_shaft", sa.Double(), nullable=False),
        sa.Column("alpha_housing", sa.Double(), nullable=False),
        sa.Column("cov", sa.JSON(), nullable=False),
        sa.Column("residual_rms_um", sa.Double(), nullable=True),
        sa.Column("residual_max_um", sa.Double(), nullable=True),
        sa.Column("explained", sa.Boolean(), nullable=False),
        sa.Column("temperatures_sha256", sa.String(length=64), nullable=False),
        sa.Column("canlog_sha256", sa.String(length=64), nullable=True),
        sa.Column("displacements_sha256", sa.String(length=64), nullable=False),
        sa.Column("report", sa.JSON(), nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_mechanics_calibrations")),
    )
    op.create_index(op.f("ix_mechanics_calibrations_at"), "mechanics_calibrations", ["at"], unique=False)


def downgrade() -> None:
    op.drop_index(op.f("ix_mechanics_calibrations_at"), table_name="mechanics_calibrations")
    op.drop_table("mechanics_calibrations")
