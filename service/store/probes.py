"""Probe readings in the database: ``ProbeMeasurement`` <-> ``probe_measurements`` rows.

Every reading taken (``POST /compensation/measurements``), absorbed or not, is written through the buffered
writer (``probe_record``); the newest ``PROBES_KEPT`` are restored at start-up (``restore_probes``) and the
accepted ones measured after the restored commissioning are replayed into the mechanical posterior
(``service.serve.compensation``). A stored row that is not a reading (a feature row of the wrong size, an sd
not > 0) raises ``StoredProbeError`` naming the row; the row stays in the table.
"""

from __future__ import annotations

import math
from dataclasses import replace
from datetime import datetime
from typing import TYPE_CHECKING

from service.contracts.probe import PROBES_KEPT, ProbeMeasurement
from service.store.errors import RecordRejectedError

if TYPE_CHECKING:
    from sqlalchemy.orm import Session

    from service.store.models import ProbeMeasurementRow

__all__ = ["StoredProbeError", "probe_from_row", "probe_record", "restore_probes"]


class StoredProbeError(RecordRejectedError):
    """A stored probe reading that cannot be used; the message names the row and why."""


def probe_record(m: ProbeMeasurement, recorded_at: datetime) -> ProbeMeasurement:
    """The reading the writer stores for ``m``: ``m`` taken at ``recorded_at`` (UTC)."""
    return replace(m, recorded_at=recorded_at)


def probe_from_row(row: ProbeMeasurementRow) -> ProbeMeasurement:
    """The ``ProbeMeasurement`` stored in ``row``; ``StoredProbeError`` if it is not one."""
    try:
        flat = [float(v) for v in row.features]  # type: ignore[arg-type]
        if len(flat) != 6 or not all(math.isfinite(v) for v in flat):
            raise ValueError(f"features: expected 6 finite values (2×3), got {len(flat)}")
        sd = float(row.sd_um)
        if not sd > 0.0:
            raise ValueError(f"sd_um: must be > 0, got {sd}")
        return ProbeMeasurement(
            at=row.at,
            axial_um=float(row.axial_um),
            sd_um=sd,
            features=(tuple(flat[0:3]), tuple(flat[3:6])),
            field_var_um2=float(row.field_var_um2),
            predicted_um=float(row.predicted_um),
            sigma_um=float(row.sigma_um),
            innovation_um=float(row.innovation_um),
            accepted=bool(row.accepted),
            offset_step=bool(row.offset_step),
            set_by=str(row.set_by),
            source=str(row.source),
            id=int(row.id),
            recorded_at=row.recorded_at,
        )
    except (TypeError, ValueError) as err:
        raise StoredProbeError(f"probe_measurements row {row.id}: {err}") from err


def restore_probes(session: Session) -> tuple[ProbeMeasurement, ...]:
    """The newest stored readings, oldest first; ``StoredProbeError`` for the first unusable one."""
    from service.store.repository import recent_probe_measurements

    return tuple(probe_from_row(r) for r in recent_probe_measurements(session, limit=PROBES_KEPT))
