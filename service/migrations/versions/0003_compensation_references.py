"""compensation_references: the compensation zero (issue 26), restored at start-up

Written by hand after ``service/store/models.py`` (``CompensationReferenceRow``), in the style of ``0002``: the
UTC type decorator is written as its implementation type, so this script never imports application code.

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-27 12:45:00 UTC
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "compensation_references",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("temperature_c", sa.Double(), nullable=False),
        sa.Column("sd_c", sa.Double(), nullable=False),
        sa.Column("source", sa.String(length=16), nullable=False),
        sa.Column("set_by", sa.String(length=64), nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_compensation_references")),
    )
    op.create_index(op.f("ix_compensation_references_at"), "compensation_references", ["at"], unique=False)


def downgrade() -> None:
    op.drop_index(op.f("ix_compensation_references_at"), table_name="compensation_references")
    op.drop_table("compensation_references")
