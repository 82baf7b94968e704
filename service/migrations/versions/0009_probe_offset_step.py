"""probe_measurements.offset_step: a reading absorbed as a step of the fixture offset (issue 40)

The probe filter estimates a fixture or tool-holder offset b beside the mechanics (``service.estimate.probe``);
a gated reading right after a consistent gated one is absorbed as a step of b, and the replay at start-up must
know which readings were (it takes the stored decisions instead of re-running the gate). Rows written before
this revision read as false (no step): they replay into the same model.

Written by hand. Revision ID: 0009, Revises: 0008
Create Date: 2026-11-29 12:30:00 UTC
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0009"
down_revision = "0008"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("probe_measurements") as batch:
        batch.add_column(sa.Column("offset_step", sa.Boolean(), nullable=False, server_default=sa.false()))


def downgrade() -> None:
    with op.batch_alter_table("probe_measurements") as batch:
        batch.drop_column("offset_step")
