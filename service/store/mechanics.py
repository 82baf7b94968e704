"""Commissionings of the growth's mechanics in the database: ``MechanicsCalibration`` <->
``mechanics_calibrations`` rows.

Every commissioning stored (``chtc commission growth --url``, ``POST /compensation/mechanics``) is written
through the buffered writer (``mechanics_record``); the newest is restored at start-up
(``restore_mechanics``) and serves ``/compensation``. A stored row that is not a calibration (a restraint
outside [0, 1], a covariance of the wrong size) raises ``StoredMechanicsError`` naming the row; the row stays
in the table.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from service.contracts.mechanics import MechanicsCalibration, MechanicsError
from service.store.errors import RecordRejectedError

if TYPE_CHECKING:
    from sqlalchemy.orm import Session

    from service.store.models import MechanicsCalibrationRow

__all__ = ["StoredMechanicsError", "mechanics_from_row", "mechanics_record", "restore_mechanics"]


class StoredMechanicsError(RecordRejectedError):
    """A stored commissioning that cannot be used; the message names the row and why."""


def mechanics_record(cal: MechanicsCalibration) -> MechanicsCalibration:
    """The record the writer stores for ``cal``: the calibration itself (``MechanicsCalibration.values``)."""
    return cal


def mechanics_from_row(row: MechanicsCalibrationRow) -> MechanicsCalibration:
    """The ``MechanicsCalibration`` stored in ``row``; ``StoredMechanicsError`` if it is not one."""
    try:
        flat = [float(v) for v in row.cov]  # type: ignore[arg-type]
        if len(flat) != 9:
            raise MechanicsError(f"cov: expected 9 values (3×3), got {len(flat)}")
        sources = {
            "temperatures": str(row.temperatures_sha256),
            "displacements": str(row.displacements_sha256),
        }
        if row.canlog_sha256 is not None:
            sources["canlog"] = str(row.canlog_sha256)
        return MechanicsCalibration(
            x=(float(row.restraint), float(row.alpha_shaft), float(row.alpha_housing)),
            cov=(tuple(flat[0:3]), tuple(flat[3:6]), tuple(flat[6:9])),
            at=row.at,
            set_by=str(row.set_by),
            source=str(row.source),
            sources=sources,
            residual_rms_um=float("nan") if row.residual_rms_um is None else float(row.residual_rms_um),
            residual_max_um=float("nan") if row.residual_max_um is None else float(row.residual_max_um),
            explained=bool(row.explained),
            report=dict(row.report or {}),
        )
    except (MechanicsError, TypeError, ValueError) as err:
        raise StoredMechanicsError(f"mechanics_calibrations row {row.id}: {err}") from err


def restore_mechanics(session: Session) -> MechanicsCalibration | None:
    """The newest stored commissioning, None if there is none; ``StoredMechanicsError`` if it is unusable."""
    from service.store.repository import last_mechanics_calibration

    row = last_mechanics_calibration(session)
    return None if row is None else mechanics_from_row(row)
