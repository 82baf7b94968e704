"""The live state's checkpoint in the database: ``LiveCheckpoint`` <-> the one ``live_state`` row.

The core hands a checkpoint (``LiveCheckpoint.values`` is its row) to the buffered writer every
``engine.live_checkpoint_s`` of sample time; the writer replaces the stored row
(``service.store.repository.write_records``), so the table holds one row whatever the uptime.
``restore_live_state`` reads it at start-up. A stored row that is not a checkpoint (a damaged payload, a bad
shape) raises ``StoredLiveStateError`` naming the row; the row stays, the service starts the filter from its
prior and the next checkpoint replaces it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from service.contracts.checkpoint import CheckpointError, LiveCheckpoint
from service.store.errors import RecordRejectedError

if TYPE_CHECKING:
    from sqlalchemy.orm import Session

__all__ = ["StoredLiveStateError", "restore_live_state"]


class StoredLiveStateError(RecordRejectedError):
    """A stored live-state checkpoint that cannot be used; the message names the row and why."""


def restore_live_state(session: Session) -> LiveCheckpoint | None:
    """The stored checkpoint, None if there is none; ``StoredLiveStateError`` if it is unusable."""
    from service.store.repository import last_live_state

    row = last_live_state(session)
    if row is None:
        return None
    try:
        return LiveCheckpoint.from_parts(
            bytes(row.payload),
            t=row.at.timestamp(),
            model_version=str(row.model_version),
            converged=bool(row.converged),
            inputs=(float(row.ambient_c), float(row.speed_rpm), float(row.torque_nm)),
        )
    except CheckpointError as err:
        raise StoredLiveStateError(f"live_state row {row.id}: {err}") from err
