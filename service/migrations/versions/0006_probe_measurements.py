"""probe_measurements: probe readings in service (issue 27 item 3), replayed into the mechanics at start-up

Written by hand after ``service/store/models.py`` (``ProbeMeasurementRow``), in the style of ``0005``: the
UTC type decorator is written as its implementation type, so this script never imports application code.

Revision ID: 0006
Revises: 0005
Create Date: 2026-11-27 21:00:00 UTC
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
        "probe_measurements",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("recorded_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("axial_um", sa.Double(), nullable=False),
        sa.Column("sd_um", sa.Double(), nullable=False),
        sa.Column("features", sa.JSON(), nullable=False),
        sa.Column("field_var_um2", sa.Double(), nullable=False),
        sa.Column("predicted_um", sa.Double(), nullable=False),
        sa.Column("sigma_um", sa.Double(), nullable=False),
        sa.Column("innovation_um", sa.Double(), nullable=False),
        sa.Column("accepted", sa.Boolean(), nullable=False),
        sa.Column("set_by", sa.String(length=64), nullable=False),
        sa.Column("source", sa.String(length=16), nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_probe_measurements")),
    )
    op.create_index(op.f("ix_probe_measurements_at"), "probe_measurements", ["at"], unique=False)


def downgrade() -> None:
    op.drop_index(op.f("ix_probe_measurements_at"), table_name="probe_measurements")
    op.drop_table("probe_measurements")
