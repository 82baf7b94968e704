"""live_state: the live state's newest checkpoint (issue 26: a restart with stored state resumes the filter)

Written by hand after ``service/store/models.py`` (``LiveStateRow``), in the style of ``0002``: the UTC type
decorator is written as its implementation type, so this script never imports application code.

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-27 19:50:00 UTC
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "live_state",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("model_version", sa.String(length=64), nullable=False),
        sa.Column("converged", sa.Boolean(), nullable=False),
        sa.Column("ambient_c", sa.Double(), nullable=False),
        sa.Column("speed_rpm", sa.Double(), nullable=False),
        sa.Column("torque_nm", sa.Double(), nullable=False),
        sa.Column("payload", sa.LargeBinary(), nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_live_state")),
    )


def downgrade() -> None:
    op.drop_table("live_state")
