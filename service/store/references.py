"""Compensation zeros in the database: ``CompensationReference`` <-> ``compensation_references`` rows.

Every zero set (``POST /compensation/reference``, ``chtc commission zero``, the first start when configured)
is written through the buffered writer (``reference_record``); the newest is restored at start-up
(``restore_reference``), so a controller zeroed cold keeps its zero across restarts. A stored row that is
not a reference (a non-finite temperature, an unknown source) raises ``StoredReferenceError`` naming the
row; the row stays in the table.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from service.contracts.reference import CompensationReference, ReferenceError
from service.store.errors import RecordRejectedError

if TYPE_CHECKING:
    from sqlalchemy.orm import Session

    from service.store.models import CompensationReferenceRow

__all__ = ["StoredReferenceError", "reference_from_row", "reference_record", "restore_reference"]


class StoredReferenceError(RecordRejectedError):
    """A stored compensation zero that cannot be used; the message names the row and why."""


def reference_record(ref: CompensationReference) -> CompensationReference:
    """The record the writer stores for ``ref``: the reference itself (``CompensationReference.values``)."""
    return ref


def reference_from_row(row: CompensationReferenceRow) -> CompensationReference:
    """The ``CompensationReference`` stored in ``row``; ``StoredReferenceError`` if it is not one."""
    try:
        return CompensationReference(
            temperature_c=float(row.temperature_c),
            sd_c=float(row.sd_c),
            at=row.at,
            source=str(row.source),
            set_by=str(row.set_by),
        )
    except (ReferenceError, TypeError, ValueError) as err:
        raise StoredReferenceError(f"compensation_references row {row.id}: {err}") from err


def restore_reference(session: Session) -> CompensationReference | None:
    """The newest stored zero, None if there is none; ``StoredReferenceError`` if it is unusable."""
    from service.store.repository import last_compensation_reference

    row = last_compensation_reference(session)
    return None if row is None else reference_from_row(row)
